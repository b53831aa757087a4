"""The hierarchical task controller over ``x = [qdd; tau]``, solved at the control rate.

- :mod:`.rows`: the row types every task and haptic constraint returns
  (:class:`Equality` ``A x = b``, :class:`Inequality` ``G x <= h``);
- :mod:`.tasks`: one class per task (dynamics, joint limits, fixed walls, minimum acceleration,
  motion tasks), each with a frozen configuration;
- :mod:`.hierarchy`: lexicographic least squares with inequalities in one call to DAQP's
  hierarchical mode;
- :mod:`.cascade`: the same problem level by level with quadprog (cross-check and fallback);
- :mod:`.controller`: the paper's priorities, torque clamping and fault handling.
- :mod:`.reductions`: the cheap finiteness test and direct reductions both use on the hot path.
"""

from .cascade import CascadeResult, solve_cascade
from .controller import (
    LEVEL_NAMES,
    ControllerConfig,
    ControlOutput,
    ControlStatus,
    HierarchicalController,
)
from .hierarchy import (
    DAQP_INF,
    HierarchicalSolver,
    HierarchyConfig,
    HierarchyResult,
    SolveStatus,
    solve_hierarchy,
)
from .rows import Equality, Inequality, empty_inequality
from .tasks import (
    EquationOfMotion,
    EquationOfMotionConfig,
    FixedWalls,
    FixedWallsConfig,
    HipMotionConfig,
    HipMotionTask,
    JointMotionConfig,
    JointMotionTask,
    JointPositionLimit,
    JointPositionLimitConfig,
    JointVelocityLimit,
    JointVelocityLimitConfig,
    MinimizeAcceleration,
    MinimizeAccelerationConfig,
    TorqueLimit,
    TorqueLimitConfig,
)

__all__ = [
    "DAQP_INF",
    "LEVEL_NAMES",
    "CascadeResult",
    "ControlOutput",
    "ControlStatus",
    "ControllerConfig",
    "Equality",
    "EquationOfMotion",
    "EquationOfMotionConfig",
    "FixedWalls",
    "FixedWallsConfig",
    "HierarchicalController",
    "HierarchicalSolver",
    "HierarchyConfig",
    "HierarchyResult",
    "HipMotionConfig",
    "HipMotionTask",
    "Inequality",
    "JointMotionConfig",
    "JointMotionTask",
    "JointPositionLimit",
    "JointPositionLimitConfig",
    "JointVelocityLimit",
    "JointVelocityLimitConfig",
    "MinimizeAcceleration",
    "MinimizeAccelerationConfig",
    "SolveStatus",
    "TorqueLimit",
    "TorqueLimitConfig",
    "empty_inequality",
    "solve_cascade",
    "solve_hierarchy",
]
