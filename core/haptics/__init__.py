"""Haptic constraints built from the fused surface: positional, velocity and force.

Each constraint is a class built from a frozen config; ``rows(state, surface, dt)`` returns an
:class:`~hapticloud.core.control.rows.Inequality` ``G x <= h`` over ``x = [qdd; tau]`` (one row
when active, none when the surface is beyond the activation distance). ``state`` is the robot's
:class:`HipState` of the tick, ``surface`` a :class:`SurfacePoint` (or the fusion's output).
Signs and the shared quantities are explained in :mod:`.distance`.
"""

from .distance import (
    HapticState,
    HipState,
    SurfacePoint,
    constraint_jacobian,
    d_proj,
    haptic_state,
    trusted_d_proj,
)
from .force import ForceConstraint, ForceConstraintConfig, contact_force_n, effective_mass_kg
from .iso15066 import BODY_REGIONS, BodyRegion, body_region, max_transient_speed_mps
from .positional import PositionalConstraint, PositionalConstraintConfig
from .velocity import VelocityConstraint, VelocityConstraintConfig, approach_speed_bound

__all__ = [
    "BODY_REGIONS",
    "BodyRegion",
    "ForceConstraint",
    "ForceConstraintConfig",
    "HapticState",
    "HipState",
    "PositionalConstraint",
    "PositionalConstraintConfig",
    "SurfacePoint",
    "VelocityConstraint",
    "VelocityConstraintConfig",
    "approach_speed_bound",
    "body_region",
    "constraint_jacobian",
    "contact_force_n",
    "d_proj",
    "effective_mass_kg",
    "haptic_state",
    "max_transient_speed_mps",
    "trusted_d_proj",
]
