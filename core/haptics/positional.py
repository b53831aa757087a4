"""Positional constraint (paper eqs. 9-11): the predicted penetration stays non-positive.

With the horizon ``T = kp * dt`` the second-order prediction of the free distance must stay
non-negative::

    d_proj + T d_dot + T^2/2 (J_c qdd + Jdc_qd) >= 0,      d_dot = J_c qd (+ d_dot_surface)

which is the paper's eq. 9 (``kp dt`` and ``kp^2 dt^2 / 2`` multiply the velocity and the
acceleration terms) written as one row of ``G x <= h`` over ``x = [qdd; tau]``, divided by
``T^2/2`` so that it is in m/s^2 like every other acceleration task::

    G = [-J_c, 0]        h = 2 (d_proj + T d_dot) / T^2 + Jdc_qd

Where the row binds it makes the distance a damped spring, ``d_ddot + (2/T) d_dot + (2/T^2) d = 0``:
natural frequency ``sqrt(2)/T``, damping ratio ``1/sqrt(2)``. So ``kp`` sets the stiffness through
the horizon: **a larger kp is softer** and acts earlier; ``kp = 1`` (one tick) is the stiffest.

Beyond the paper (``surface_velocity_feedforward``): ``d_dot`` also counts the surface's own
velocity along the normal, so a surface coming towards the HIP pushes it back before it
penetrates. The surface's acceleration is not modelled (assumed constant velocity over ``T``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from ..config import StageConfig, param
from ..control.rows import Inequality, empty_inequality
from .distance import HapticState, HipState, check_dt, haptic_state


@dataclass(frozen=True)
class PositionalConstraintConfig(StageConfig):
    """Parameters of :class:`PositionalConstraint`."""

    _path: ClassVar[str] = "haptics.positional"

    kp: float = param(
        30.0,
        lo=1.0,
        hi=1000.0,
        log_scale=True,
        doc="prediction horizon in control ticks, T = kp dt (larger = softer spring)",
    )
    activation_distance_m: float = param(
        0.10, lo=0.0, hi=2.0, unit="m", doc="no rows while d_proj is above this distance"
    )
    surface_velocity_feedforward: bool = param(
        True, doc="count the surface's velocity along n in d_dot (false = the paper)"
    )

    def natural_frequency_hz(self, dt: float) -> float:
        """Natural frequency (Hz) of the spring the binding constraint makes, for period ``dt``."""
        return math.sqrt(2.0) / (self.kp * check_dt(dt)) / (2.0 * math.pi)


class PositionalConstraint:
    """Positional haptic constraint: one inequality row over ``[qdd; tau]`` when near the surface.

    Parameters
    ----------
    config
        Gains and switches; defaults if omitted.
    name
        Name given to the rows (shown when the problem is inspected).
    """

    default_name: ClassVar[str] = "haptic_positional"

    def __init__(
        self, config: PositionalConstraintConfig | None = None, name: str = default_name
    ) -> None:
        self.config = config or PositionalConstraintConfig()
        self.name = name

    def rows(
        self,
        state: HipState,
        surface: Any,
        dt: float,
        *,
        haptic: HapticState | None = None,
    ) -> Inequality:
        """The constraint's rows for this tick.

        Parameters
        ----------
        state
            Robot-side HIP quantities of this tick.
        surface
            :class:`~.distance.SurfacePoint` or any object with ``centroid``, ``normal`` (and
            optionally ``velocity``).
        dt
            Control period (s).
        haptic
            ``haptic_state(state, surface)`` if the caller has it already (several constraints
            on one surface share it); then ``state`` and ``surface`` are not read.

        Returns
        -------
        Inequality
            One row ``G x <= h`` (m/s^2) with ``x = [qdd; tau]``, or no rows if the surface is
            farther than ``activation_distance_m``.
        """
        hs = haptic if haptic is not None else haptic_state(state, surface)
        dt = check_dt(dt)
        n = hs.n_joints
        if hs.d_proj > self.config.activation_distance_m:
            return empty_inequality(2 * n, self.name)
        G = np.zeros((1, 2 * n))
        G[0, :n] = -hs.J_c
        return Inequality(G, np.array([self.bound(hs, dt)]), self.name)

    def bound(self, hs: HapticState, dt: float) -> float:
        """The row's right-hand side ``2 (d_proj + T d_dot) / T^2 + Jdc_qd`` (m/s^2), ``T = kp dt``.

        The constraint's one formula: :meth:`rows` and the haptic loop's shared motion row (whose
        ``G = [-J_c, 0]`` is this row's) both call it. ``dt`` is a checked period.
        """
        cfg = self.config
        horizon = cfg.kp * dt
        d_dot = hs.distance_rate(cfg.surface_velocity_feedforward)
        return 2.0 * (hs.d_proj + horizon * d_dot) / (horizon * horizon) + hs.Jdc_qd
