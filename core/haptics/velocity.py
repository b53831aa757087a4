"""Velocity constraint (paper eqs. 12-14): the approach speed is bounded by the distance.

The approach speed is ``s = -d_dot`` (positive when the HIP and the surface come closer). Its
bound ``v_c(d)`` (eq. 12) is ``v_min`` below ``d_offset``, ``v_max`` above ``d_offset +
d_width`` and linear between. It is enforced one step ahead with the gain ``kv``
(``K = kv * dt``): the approach speed predicted ``K`` ahead must respect the bound::

    s - K (J_c qdd + Jdc_qd) <= v_c(d_proj)

as one row of ``G x <= h`` over ``x = [qdd; tau]``, divided by ``K`` so that it is in m/s^2::

    G = [-J_c, 0]        h = (v_c(d_proj) + d_dot) / K + Jdc_qd

Where the row binds, an excess approach speed decays with the time constant ``K``: a larger
``kv`` is softer; ``kv = 1`` removes it in one tick.

Beyond the paper (``surface_velocity_feedforward``, on by default): the bound applies to the HIP's
velocity **relative to the surface**, ``d_dot = J_c qd - n . v_s``, so a surface moving towards
the HIP pushes the HIP away in time instead of waiting for the positional constraint (the paper's
Sec. VI names this as the remedy for the shrinking margin of Fig. 12). With the switch off,
``d_dot = J_c qd`` as in the paper, which lets the two be compared.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from ..config import StageConfig, param
from ..control.rows import Inequality, empty_inequality
from ..errors import ConfigError
from .distance import HapticState, HipState, check_dt, haptic_state

#: Below this ramp width (m) the bound is a step at ``d_offset`` (no division by ~0).
MIN_RAMP_WIDTH_M = 1.0e-9


def approach_speed_bound(
    d_proj_m: float, v_min_mps: float, v_max_mps: float, d_offset_m: float, d_width_m: float
) -> float:
    """``v_c(d)`` of the paper's eq. 12 (m/s).

    ``v_min_mps`` for ``d_proj_m < d_offset_m``, ``v_max_mps`` for ``d_proj_m > d_offset_m +
    d_width_m``, linear in between. A width below :data:`MIN_RAMP_WIDTH_M` is a step at
    ``d_offset_m``, where the lower value ``v_min_mps`` applies (the safer side).
    """
    excess = d_proj_m - d_offset_m
    if excess <= 0.0:
        return v_min_mps
    if d_width_m < MIN_RAMP_WIDTH_M or excess >= d_width_m:
        return v_max_mps
    return v_min_mps + (excess / d_width_m) * (v_max_mps - v_min_mps)


@dataclass(frozen=True)
class VelocityConstraintConfig(StageConfig):
    """Parameters of :class:`VelocityConstraint`.

    Cross-field rules: ``v_min_mps <= v_max_mps``; ``activation_distance_m >= d_offset_m +
    d_width_m`` (rows appear before the ramp begins, so switching on never cuts the ramp).
    """

    _path: ClassVar[str] = "haptics.velocity"

    v_min_mps: float = param(
        0.05, lo=0.0, hi=5.0, unit="m/s", doc="approach speed allowed closer than d_offset"
    )
    v_max_mps: float = param(
        1.0, lo=0.0, hi=5.0, unit="m/s", doc="approach speed allowed beyond d_offset + d_width"
    )
    d_offset_m: float = param(
        0.0, lo=-0.1, hi=1.0, unit="m", doc="distance below which only v_min is allowed"
    )
    d_width_m: float = param(
        0.10, lo=0.0, hi=1.0, unit="m", doc="width of the linear ramp from v_min to v_max"
    )
    kv: float = param(
        10.0,
        lo=1.0,
        hi=1000.0,
        log_scale=True,
        doc="enforcement horizon in control ticks, K = kv dt (larger = softer)",
    )
    activation_distance_m: float = param(
        0.15, lo=0.0, hi=2.0, unit="m", doc="no rows while d_proj is above this distance"
    )
    surface_velocity_feedforward: bool = param(
        True, doc="bound the speed relative to the moving surface (false = the paper)"
    )

    def check(self) -> None:
        if not self.v_min_mps <= self.v_max_mps:
            raise ConfigError(
                f"v_min_mps = {self.v_min_mps}: must be <= v_max_mps ({self.v_max_mps})"
            )
        ramp_end = self.d_offset_m + self.d_width_m
        if not self.activation_distance_m >= ramp_end:
            raise ConfigError(
                f"activation_distance_m = {self.activation_distance_m}: must be >= "
                f"d_offset_m + d_width_m ({ramp_end:g} m)"
            )

    def bound(self, d_proj_m: float) -> float:
        """``v_c(d_proj_m)`` (m/s) with these parameters."""
        return approach_speed_bound(
            d_proj_m, self.v_min_mps, self.v_max_mps, self.d_offset_m, self.d_width_m
        )


class VelocityConstraint:
    """Velocity haptic constraint: one inequality row over ``[qdd; tau]`` when near the surface.

    Parameters
    ----------
    config
        Speeds, distances, gain and switches; defaults if omitted.
    name
        Name given to the rows.
    """

    default_name: ClassVar[str] = "haptic_velocity"

    def __init__(
        self, config: VelocityConstraintConfig | None = None, name: str = default_name
    ) -> None:
        self.config = config or VelocityConstraintConfig()
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
            optionally ``velocity``, used by the feed-forward).
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

    def bound(self, hs: HapticState, dt: float, speed_mps: float | None = None) -> float:
        """The row's right-hand side ``(v_c(d_proj) + d_dot) / K + Jdc_qd`` (m/s^2), ``K = kv dt``.

        The constraint's one formula: :meth:`rows` and the haptic loop's shared motion row both
        call it. ``speed_mps`` replaces ``v_c(d_proj)`` (the loop's cap on the approach speed
        while a surface is held). ``dt`` is a checked period.
        """
        cfg = self.config
        speed = cfg.bound(hs.d_proj) if speed_mps is None else speed_mps
        gain_time = cfg.kv * dt
        return (speed + hs.distance_rate(cfg.surface_velocity_feedforward)) / gain_time + hs.Jdc_qd
