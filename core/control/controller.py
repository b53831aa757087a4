"""The hierarchical task controller: the paper's priorities, solved each tick, torques clamped.

Levels (Table I of the paper, plus a null-space level for the motion task):

1. equation of motion (+ torque limits, by default: see ``torque_limit_level``)
2. joint position and velocity safety limits
3. fixed collision constraints: static virtual walls at the HIP
4. online collision avoidance: the haptic constraint rows handed in each tick
5. minimise joint accelerations, or the session's motion task when one is given
6. minimise joint accelerations in what the motion task leaves free (empty without one)

Torque limits sit with the equation of motion by default. They are what the drives can do, so
hard: the joint limits below are then met as well as the available torque allows, and the final
clamp changes the solution only by solver rounding. Set ``torque_limit_level = "safety"`` to put
them at level 2, beside the joint limits, as the paper's list can also be read; the clamp then
does the limiting when those conflict, and the report describes the clamped torques.

After the solve, ``tau`` is rebuilt from ``qdd`` through the model (``tau = M qdd + h - tau_int``)
because DAQP holds its hard first level only up to drift when a lower level is badly violated;
after clamping, ``qdd`` is recomputed from the torque actually sent. The dynamics residual of the
output is therefore at rounding level (< 1e-8) in every case.

Any NaN or inf in the inputs gives zero torque and status ``FAULT``; the output is never NaN and
never outside ``[-tau_max, tau_max]``.

Cost (sample 6-joint arm, one core, single-threaded BLAS; ``OPENBLAS_NUM_THREADS=1 hapticloud
bench loop``, 2026-11-21): a step that solves the hierarchy takes ~115 us median in the closed
loop of the ``impacts`` scene (16 % of its ticks; the hierarchy's solve ~68 us of it, the DAQP
call ~15 us), ~70 us when replayed with warm caches; a step whose transparent torques already
satisfy every constraint skips the solver (~11 us). ``pytest tests/core/test_controller.py -m slow
-s`` measures the step on its own.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..config import StageConfig, nested, param
from ..errors import InputError
from .hierarchy import DAQP_INF, HierarchicalSolver, HierarchyConfig, SolveStatus, StackedLevels
from .reductions import and_reduce, finite_total, max_reduce
from .rows import Equality, Inequality
from .tasks import (
    EquationOfMotion,
    EquationOfMotionConfig,
    FixedWalls,
    FixedWallsConfig,
    JointLimitCheck,
    JointPositionLimit,
    JointPositionLimitConfig,
    JointVelocityLimit,
    JointVelocityLimitConfig,
    MinimizeAcceleration,
    MinimizeAccelerationConfig,
    TorqueLimit,
    TorqueLimitConfig,
    shaped_array,
)

FloatArray = NDArray[np.float64]

#: Names of the controller's levels, in priority order (index = level - 1).
LEVEL_NAMES: tuple[str, ...] = (
    "equation_of_motion",
    "joint_limits",
    "fixed_walls",
    "collision_avoidance",
    "motion",
    "null_space",
)

# Torque beyond the limit by less than this (relative) is solver drift, not clamping.
_CLAMP_RTOL = 1e-6


class ControlStatus(StrEnum):
    """Outcome of one controller step."""

    #: levels 1-5 hold (level 6, the motion task's null space, never counts).
    OK = "ok"
    #: some level of 2-5 was sacrificed (a wall stops the motion task, ...).
    RELAXED = "relaxed"
    #: no solver answer: torque is the model's compensation torque ``h``, clamped.
    SOLVER_FAILED = "solver_failed"
    #: NaN or inf in the inputs: zero torque.
    FAULT = "fault"


# Solver outcomes that carry a usable x. A "top level infeasible" can only be drift here: the
# dynamics with torque limits are always feasible for finite inputs (qdd is free).
_USABLE = (SolveStatus.OPTIMAL, SolveStatus.RELAXED, SolveStatus.TOP_LEVEL_INFEASIBLE)


@dataclass(frozen=True)
class ControllerConfig(StageConfig):
    """Parameters of :class:`HierarchicalController` (one table, one sub-table per task)."""

    torque_limit_level: str = param(
        "dynamics",
        choices=("dynamics", "safety"),
        doc="level of |tau| <= tau_max: 1 with the dynamics (hard), or 2 with the joint limits",
    )
    torque_metric_weight: float = param(
        1.0,
        lo=1e-6,
        hi=1e6,
        log_scale=True,
        doc="weight of tau against qdd in the solver's metric (tie-break, row lengths)",
    )
    equation_of_motion: EquationOfMotionConfig = nested(EquationOfMotionConfig)
    position_limit: JointPositionLimitConfig = nested(JointPositionLimitConfig)
    velocity_limit: JointVelocityLimitConfig = nested(JointVelocityLimitConfig)
    torque_limit: TorqueLimitConfig = nested(TorqueLimitConfig)
    walls: FixedWallsConfig = nested(FixedWallsConfig)
    min_acceleration: MinimizeAccelerationConfig = nested(MinimizeAccelerationConfig)
    solver: HierarchyConfig = nested(HierarchyConfig)


class StepInputs(NamedTuple):
    """What one :meth:`HierarchicalController.step` works from, converted to float64 and
    shape-checked (the haptic loop builds it from the robot model's validated state)."""

    q: FloatArray
    qd: FloatArray
    M: FloatArray
    h: FloatArray
    dt: float
    hip_position: FloatArray | None
    hip_jacobian: FloatArray | None
    hip_jdot_qd: FloatArray | None
    haptic_rows: Sequence[Inequality]
    wall_rows: Sequence[Inequality]
    motion: Equality | None
    interaction_torque: FloatArray | None


class ControlOutput(NamedTuple):
    """What :meth:`HierarchicalController.step` returns.

    Attributes
    ----------
    tau
        Joint torques to command, shape ``(n,)``: finite, within ``[-tau_max, tau_max]``.
    qdd
        Joint accelerations the model predicts for ``tau``, shape ``(n,)``.
    status
        :class:`ControlStatus`.
    level_slack
        Norm of each level's violation (rows in their own units), shape ``(6,)``, see
        :data:`LEVEL_NAMES`.
    solve_us
        Time of the hierarchy solve (assembly, DAQP, report), microseconds.
    clamped
        True when the clamp changed the solver's torque by more than rounding.
    step_us
        Time of the whole step, microseconds.
    fault
        Why the status is ``FAULT`` or ``SOLVER_FAILED``; empty otherwise.
    """

    tau: FloatArray
    qdd: FloatArray
    status: ControlStatus
    level_slack: FloatArray
    solve_us: float
    clamped: bool
    step_us: float = 0.0
    fault: str = ""


def _real(arr: NDArray) -> FloatArray:
    """``arr`` as float64 by the solver's own rule (what stacking rows would accept)."""
    try:
        return np.concatenate((arr,), dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("task rows: expected real numbers") from None


def _nonfinite(**arrays: Any) -> list[str]:
    """Names of the arguments holding NaN or inf (``None`` is skipped)."""
    return [k for k, v in arrays.items() if v is not None and not np.isfinite(v).all()]


def _bad_rows(rows: Sequence[Inequality | Equality]) -> list[str]:
    """Names of row sets with NaN/inf coefficients or NaN/-inf bounds (+inf bounds are fine)."""
    bad = []
    for task in rows:
        mat, vec = np.asarray(task[0]), np.asarray(task[1])
        ok = np.isfinite(mat).all() and not np.isnan(vec).any()
        ok = ok and (not (vec == -np.inf).any())
        if isinstance(task, Equality):
            ok = ok and np.isfinite(vec).all()
        if not ok:
            bad.append(task[2] or type(task).__name__)
    return bad


class HierarchicalController:
    """The hierarchical task controller of the paper, at the control rate.

    Parameters
    ----------
    config
        :class:`ControllerConfig`; defaults when ``None``.
    n_joints
        Number of joints ``n``.
    q_min, q_max, v_max, tau_max
        Joint limits, each shape ``(n,)``; ``tau_max`` positive and finite.
    wall_points, wall_normals
        Static virtual planes (``(k, 3)`` each, world frame, normals to the allowed side);
        none by default.

    Examples
    --------
    >>> import numpy as np
    >>> ctrl = HierarchicalController(None, 2, [-1, -1], [1, 1], [2, 2], [10, 10])
    >>> out = ctrl.step([0, 0], [0, 0], np.eye(2), [1.0, -2.0], 1 / 800)
    >>> out.tau.round(6).tolist(), out.status.value
    ([1.0, -2.0], 'ok')
    """

    def __init__(
        self,
        config: ControllerConfig | None,
        n_joints: int,
        q_min: ArrayLike,
        q_max: ArrayLike,
        v_max: ArrayLike,
        tau_max: ArrayLike,
        *,
        wall_points: ArrayLike | None = None,
        wall_normals: ArrayLike | None = None,
    ) -> None:
        cfg = config if config is not None else ControllerConfig()
        self.config = cfg
        if isinstance(n_joints, bool) or not isinstance(n_joints, int | np.integer):
            raise InputError(f"n_joints = {n_joints!r}: expected a positive integer")
        n = int(n_joints)
        if n < 1:
            raise InputError(f"n_joints = {n}: expected a positive integer")
        self.n_joints = n
        for name, value in (
            ("q_min", q_min),
            ("q_max", q_max),
            ("v_max", v_max),
            ("tau_max", tau_max),
        ):
            if np.size(value) != n:
                raise InputError(f"{name}: expected {n} values, got {np.size(value)}")
        self.eom = EquationOfMotion(n, cfg.equation_of_motion)
        self.position_limit = JointPositionLimit(q_min, q_max, cfg.position_limit)
        self.velocity_limit = JointVelocityLimit(v_max, cfg.velocity_limit)
        self.torque_limit = TorqueLimit(tau_max, cfg.torque_limit)
        self.tau_max = self.torque_limit.tau_max
        self.min_acceleration = MinimizeAcceleration(n, cfg.min_acceleration)
        self.walls: FixedWalls | None = None
        if wall_points is not None or wall_normals is not None:
            if wall_points is None or wall_normals is None:
                raise InputError("wall_points, wall_normals: give both or neither")
            walls = FixedWalls(wall_points, wall_normals, n, cfg.walls)
            self.walls = walls if walls.n_walls else None
        metric = np.concatenate([np.ones(n), np.full(n, cfg.torque_metric_weight)])
        self.solver = HierarchicalSolver(2 * n, cfg.solver, metric=metric)
        self._zero = np.zeros(n)
        self._minus_tau_max = -self.tau_max
        self._clamp_threshold = self.tau_max * (1.0 + _CLAMP_RTOL)
        # Levels 1 and 2 always have the same 7 n rows (dynamics, torque, position and velocity
        # limits): their constant coefficients live in a buffer that each step only updates.
        if cfg.torque_limit_level == "dynamics":
            self._o_tau, self._o_pos, self._o_vel = n, 3 * n, 5 * n
            self._head_counts = (3 * n, 4 * n)
        else:
            self._o_pos, self._o_vel, self._o_tau = n, 3 * n, 5 * n
            self._head_counts = (n, 6 * n)
        self._allocate(7 * n + 2 * n + 8 + (0 if self.walls is None else self.walls.n_walls))

    @classmethod
    def from_robot(
        cls, robot: Any, config: ControllerConfig | None = None, **walls: ArrayLike
    ) -> HierarchicalController:
        """Build from an object with ``q_min, q_max, v_max, tau_max`` attributes (a robot model)."""
        q_min = np.asarray(robot.q_min, dtype=np.float64).reshape(-1)
        return cls(config, q_min.size, q_min, robot.q_max, robot.v_max, robot.tau_max, **walls)

    # ----- one tick -------------------------------------------------------------------------------
    def step(
        self,
        q: ArrayLike,
        qd: ArrayLike,
        mass_matrix: ArrayLike,
        nonlinear_effects: ArrayLike,
        dt: float,
        *,
        hip_position: ArrayLike | None = None,
        hip_jacobian: ArrayLike | None = None,
        hip_jdot_qd: ArrayLike | None = None,
        haptic_rows: Sequence[Inequality] = (),
        wall_rows: Sequence[Inequality] = (),
        motion: Equality | None = None,
        interaction_torque: ArrayLike | None = None,
    ) -> ControlOutput:
        """Compute the joint torques of one control tick.

        Parameters
        ----------
        q, qd
            Joint positions and velocities, shape ``(n,)``.
        mass_matrix
            ``M(q)``, shape ``(n, n)``.
        nonlinear_effects
            ``h(q, qd)`` (Coriolis, centrifugal, gravity), shape ``(n,)``.
        dt
            Control period (s), e.g. ``1/800``.
        hip_position, hip_jacobian, hip_jdot_qd
            HIP position ``(3,)``, translational Jacobian ``(3, n)`` and ``Jdot qd`` ``(3,)``, world
            frame; required when walls are configured.
        haptic_rows
            Online collision-avoidance constraints over ``x = [qdd; tau]`` (level 4).
        wall_rows
            Extra fixed-wall rows (level 3), e.g. built elsewhere.
        motion
            The session's motion task rows (level 5; e.g. :class:`~.tasks.HipMotionTask`);
            without one, level 5 minimises the joint accelerations.
        interaction_torque
            Measured interaction torque entered in the dynamics, shape ``(n,)``.

        Returns
        -------
        ControlOutput

        Raises
        ------
        InputError
            On wrong shapes or a non-positive ``dt`` (programming errors, not faults).
        """
        t0 = time.perf_counter()
        n = self.n_joints
        try:
            q = np.asarray(q, dtype=np.float64)
            qd = np.asarray(qd, dtype=np.float64)
            M = np.asarray(mass_matrix, dtype=np.float64)
            h = np.asarray(nonlinear_effects, dtype=np.float64)
            dt_value = float(dt)
        except (TypeError, ValueError):
            raise InputError(
                "q, qd, mass_matrix, nonlinear_effects, dt: expected real numbers"
            ) from None
        if q.shape != (n,) or qd.shape != (n,) or h.shape != (n,) or M.shape != (n, n):
            raise InputError(
                f"q, qd, nonlinear_effects: expected ({n},), mass_matrix ({n}, {n}); got "
                f"{q.shape}, {qd.shape}, {h.shape}, {M.shape}"
            )
        has_hip = hip_position is not None
        if self.walls is not None and not (
            has_hip and hip_jacobian is not None and hip_jdot_qd is not None
        ):
            raise InputError("hip_position, hip_jacobian, hip_jdot_qd: required with walls")

        if not math.isfinite(dt_value):
            return self._fault("non-finite input: dt", t0)
        if not dt_value > 0.0:
            raise InputError(f"dt = {dt_value}: must be positive")
        if has_hip:
            hip_position = np.asarray(hip_position, dtype=np.float64)
        if hip_jacobian is not None:
            hip_jacobian = np.asarray(hip_jacobian, dtype=np.float64)
        if hip_jdot_qd is not None:
            hip_jdot_qd = np.asarray(hip_jdot_qd, dtype=np.float64)
        if interaction_torque is not None:
            interaction_torque = np.asarray(interaction_torque, dtype=np.float64)
        return self.step_trusted(
            t0,
            StepInputs(
                q,
                qd,
                M,
                h,
                dt_value,
                hip_position,
                hip_jacobian,
                hip_jdot_qd,
                haptic_rows,
                wall_rows,
                motion,
                interaction_torque,
            ),
        )

    def step_trusted(self, t0: float, inputs: StepInputs) -> ControlOutput:
        """:meth:`step` after its argument conversion and shape checks (``t0``: its start).

        For a caller whose arrays are already float64 of the right shapes and ``dt`` a positive
        float (the haptic loop: the robot model's validated state); every check on values (NaN,
        inf) and on the rows handed in still happens here.
        """
        # q, qd, M, h and tau_int always enter rows (joint limits, dynamics) and the solver
        # rejects non-finite rows; the HIP enters rows only while a wall is near, so it gets a
        # look of its own (a sum is finite only if every entry is).
        if not finite_total((inputs.hip_position, inputs.hip_jacobian, inputs.hip_jdot_qd)):
            return self._non_finite_fault(t0, inputs)

        levels = self._stacked(inputs)
        result = self.solver.solve(levels)
        if result.status == SolveStatus.INVALID_INPUT:
            return self._non_finite_fault(t0, inputs)
        M, h, interaction_torque = inputs.M, inputs.h, inputs.interaction_torque
        if result.status not in _USABLE:
            return self._compensation(
                M, h, interaction_torque, result.solve_us, f"solver: {result.status.value}", t0
            )
        # The dynamics are the top level and always feasible (qdd is free); DAQP holds them only
        # up to drift when a lower level is badly violated, so rebuild tau from qdd exactly.
        qdd = result.x[: self.n_joints].copy()
        tau_raw = M.dot(qdd) + h
        if interaction_torque is not None:
            tau_raw -= self.config.equation_of_motion.interaction_torque_scale * interaction_torque
        tau = np.minimum(np.maximum(tau_raw, self._minus_tau_max), self.tau_max)
        # The solver never returns a non-finite x; this sum is the last line of defence.
        if not finite_total((tau, qdd)):
            return self._fault("non-finite solution", t0)
        slack, satisfied = result.level_slack, result.level_satisfied
        clamped = False
        if max_reduce(np.abs(tau_raw) - self.tau_max) > 0.0:
            # Keep qdd the model's answer to the torque actually sent; report only real clamping.
            qdd = self._predict(M, h, tau, interaction_torque)
            clamped = bool(max_reduce(np.abs(tau_raw) - self._clamp_threshold) > 0.0)
            if clamped:  # the levels are met differently now: report what is sent
                slack, satisfied = self.solver.evaluate(levels, np.concatenate([qdd, tau]))
        # Level 1 holds by construction (tau rebuilt from qdd, then clamped). Level 6 only
        # shapes the motion task's null space; it is "violated" whenever the arm moves, so it
        # does not make a step relaxed.
        slack = slack.copy()
        slack[0] = 0.0
        status = ControlStatus.OK if and_reduce(satisfied[1:5]) else ControlStatus.RELAXED
        return ControlOutput(
            tau, qdd, status, slack, result.solve_us, clamped, (time.perf_counter() - t0) * 1e6
        )

    def limit_check(self, dt: float, tol: float) -> JointLimitCheck:
        """Levels 1-2 (torque, joint position and velocity limits) as a per-joint test of one
        ``x``, their bounds widened by ``tol`` (the haptic loop's exact shortcut)."""
        T, half_T2, q_hi, q_lo = self.position_limit.check_bounds(dt, tol)
        v_horizon, v = self.velocity_limit.check_bounds(dt, tol)
        tau = self.torque_limit.check_bounds(tol)
        return JointLimitCheck(tau, T, half_T2, q_hi, q_lo, v_horizon, v)

    def _allocate(self, capacity: int) -> None:
        """Row buffers for ``capacity`` rows, with the constant rows of levels 1 and 2 filled."""
        n = self.n_joints
        A = np.zeros((capacity, 2 * n))
        bu = np.zeros(capacity)
        bl = np.full(capacity, -DAQP_INF)
        A[:n, n:] = self.eom.torque_block
        torque = self.torque_limit.rows()
        A[self._o_tau : self._o_tau + 2 * n] = torque.G
        bu[self._o_tau : self._o_tau + 2 * n] = torque.h
        A[self._o_pos : self._o_pos + 2 * n] = self.position_limit.matrix
        A[self._o_vel : self._o_vel + 2 * n] = self.velocity_limit.matrix
        self._A, self._bu, self._bl = A, bu, bl

    def _stacked(self, inputs: StepInputs) -> StackedLevels:
        """The rows of :meth:`_levels`, written straight into the solver's stacked form.

        Same values, same order, same checks (and messages) as building the row objects and
        stacking them (``tests/core/test_controller.py`` compares both); the levels as row objects
        are built only if something asks for them (the fallback cascade).
        """
        (
            q,
            qd,
            M,
            h,
            dt,
            hip_position,
            hip_jacobian,
            hip_jdot_qd,
            haptic_rows,
            wall_rows,
            motion,
            interaction_torque,
        ) = inputs
        n = self.n_joints
        solver = self.solver
        # The tasks' own argument checks, in the order _levels meets them.
        tau_int = None
        if interaction_torque is not None:
            tau_int = shaped_array(interaction_torque, (n,), "interaction_torque")
        level3: list[tuple[NDArray, NDArray, bool]] = []
        if self.walls is not None:
            walls = self.walls.rows(hip_position, hip_jacobian, hip_jdot_qd, qd, dt)
            level3.append((walls.G, walls.h, False))
        rest = self.min_acceleration.rows(qd)
        level3 += [solver.task_arrays(task, 2) for task in wall_rows]
        level4 = [solver.task_arrays(task, 3) for task in haptic_rows]
        if motion is None:
            lower = [[(rest.A, rest.b, True)], []]
        else:
            lower = [[solver.task_arrays(motion, 4)], [(rest.A, rest.b, True)]]
        head = self._head_counts[0] + self._head_counts[1]
        counts = [*self._head_counts]
        rows = head
        for level in (level3, level4, *lower):
            count = sum([vec.shape[0] for _, vec, _ in level])
            counts.append(count)
            rows += count
        if rows > self._A.shape[0]:
            self._allocate(2 * rows)
        A, bu, bl = self._A, self._bu, self._bl
        # Level 1: M qdd - tau = tau_int - h; level 2: the joint limits' bounds, each task's own.
        A[:n, :n] = M
        bl[:n] = self.eom.rhs_into(h, tau_int, bu[:n])
        self.position_limit.bounds_into(q, qd, dt, bu[self._o_pos : self._o_pos + 2 * n])
        self.velocity_limit.bounds_into(qd, dt, bu[self._o_vel : self._o_vel + 2 * n])
        # Levels 3-6 follow in order (their row counts change from tick to tick).
        r = head
        for level in (level3, level4, *lower):
            for mat, vec, eq in level:
                k = vec.shape[0]
                if not k:
                    continue
                if mat.dtype != np.float64 or vec.dtype != np.float64:
                    mat, vec = _real(mat), _real(vec)
                A[r : r + k] = mat
                bu[r : r + k] = vec
                bl[r : r + k] = vec if eq else -DAQP_INF
                r += k
        return StackedLevels(A[:r], bu[:r], bl[:r], counts, lambda: self._levels(inputs))

    def _levels(self, inputs: StepInputs) -> list[list[Equality | Inequality]]:
        qd, dt, motion = inputs.qd, inputs.dt, inputs.motion
        torque = self.torque_limit.rows()
        dynamics_level = self.config.torque_limit_level == "dynamics"
        level1: list[Equality | Inequality] = [
            self.eom.rows(inputs.M, inputs.h, inputs.interaction_torque)
        ]
        level2: list[Equality | Inequality] = [
            self.position_limit.rows(inputs.q, qd, dt),
            self.velocity_limit.rows(qd, dt),
        ]
        (level1 if dynamics_level else level2).append(torque)
        level3: list[Equality | Inequality] = list(inputs.wall_rows)
        if self.walls is not None:
            hip = (inputs.hip_position, inputs.hip_jacobian, inputs.hip_jdot_qd)
            level3.insert(0, self.walls.rows(*hip, qd, dt))
        level4: list[Equality | Inequality] = list(inputs.haptic_rows)
        rest = self.min_acceleration.rows(qd)
        if motion is None:
            return [level1, level2, level3, level4, [rest], []]
        return [level1, level2, level3, level4, [motion], [rest]]

    # ----- safe outputs ---------------------------------------------------------------------------
    @staticmethod
    def _culprits(inputs: StepInputs) -> list[str]:
        """Names of the inputs holding NaN or inf (only computed once a fault is found)."""
        bad = _nonfinite(
            q=inputs.q,
            qd=inputs.qd,
            mass_matrix=inputs.M,
            nonlinear_effects=inputs.h,
            hip_position=inputs.hip_position,
            hip_jacobian=inputs.hip_jacobian,
            hip_jdot_qd=inputs.hip_jdot_qd,
            interaction_torque=inputs.interaction_torque,
        )
        motion = [inputs.motion] if inputs.motion is not None else []
        bad += _bad_rows([*inputs.haptic_rows, *inputs.wall_rows, *motion])
        return bad or ["overflow in the rows built from the state"]

    def _predict(
        self, M: FloatArray, h: FloatArray, tau: FloatArray, interaction_torque: ArrayLike | None
    ) -> FloatArray:
        """``M^-1 (tau + tau_int - h)``; zero when ``M`` is singular."""
        rhs = tau - h
        if interaction_torque is not None:
            scale = self.config.equation_of_motion.interaction_torque_scale
            rhs = rhs + scale * np.asarray(interaction_torque, dtype=np.float64)
        try:
            qdd = np.linalg.solve(M, rhs)
        except np.linalg.LinAlgError:
            return self._zero.copy()
        return qdd if np.isfinite(qdd).all() else self._zero.copy()

    def _compensation(
        self,
        M: FloatArray,
        h: FloatArray,
        interaction_torque: ArrayLike | None,
        solve_us: float,
        reason: str,
        t0: float,
    ) -> ControlOutput:
        # No answer from any solver: hold the model's own torques, the "do nothing" of
        # level 5, so the patient still moves the arm against no added force.
        tau = np.clip(h, -self.tau_max, self.tau_max)
        qdd = self._predict(M, h, tau, interaction_torque)
        return ControlOutput(
            tau,
            qdd,
            ControlStatus.SOLVER_FAILED,
            np.full(len(LEVEL_NAMES), np.nan),
            solve_us,
            bool(np.any(np.abs(h) > self.tau_max)),
            (time.perf_counter() - t0) * 1e6,
            reason,
        )

    def _non_finite_fault(self, t0: float, inputs: StepInputs) -> ControlOutput:
        """Zero torque and a FAULT naming the inputs (as in :meth:`_culprits`) not finite."""
        return self._fault("non-finite input: " + ", ".join(self._culprits(inputs)), t0)

    def _fault(self, reason: str, t0: float) -> ControlOutput:
        n = self.n_joints
        return ControlOutput(
            np.zeros(n),
            np.zeros(n),
            ControlStatus.FAULT,
            np.full(len(LEVEL_NAMES), np.nan),
            0.0,
            False,
            (time.perf_counter() - t0) * 1e6,
            reason,
        )
