"""Parameters of the fusion stage (regression window, follower gains, staleness).

The follower gains are those of the continuous law (see :mod:`.follower`)::

    ydd = kp * e + ki * integral(e) - kd * yd        e = target - y

so ``kp`` is in 1/s², ``ki`` in 1/s³ and ``kd`` in 1/s (critically damped at natural frequency
``w``: ``kp = w**2``, ``kd = 2 w``). The follower integrates that law with backward Euler, which
is stable for every ``dt > 0`` whenever the continuous law is, so a gain set is accepted exactly
when the continuous law is stable (Routh-Hurwitz: ``kp > 0``, ``kd > 0``, ``ki < kp * kd``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..config import StageConfig, param
from ..errors import ConfigError

_WEIGHTINGS = ("exponential", "inverse")


def gain_problem(kp: float, ki: float, kd: float, prefix: str = "") -> str:
    """Why the follower law with these gains is unstable, or ``""`` if it is stable.

    Routh-Hurwitz for ``s³ + kd s² + kp s + ki``: all coefficients positive (``ki = 0`` drops
    the integral pole) and ``kd * kp > ki``. ``prefix`` is put before the gains' names.
    """
    p = prefix
    if not kp > 0.0:
        return f"{p}kp = {kp} must be > 0 (no restoring force)"
    if not kd > 0.0:
        return f"{p}kd = {kd} must be > 0 (undamped follower oscillates)"
    if ki < 0.0:
        return f"{p}ki = {ki} must be >= 0"
    if not ki < kp * kd:
        return (
            f"{p}ki = {ki} must be < {p}kp * {p}kd = {kp * kd:g} (Routh-Hurwitz); "
            "with a larger integral gain the follower diverges"
        )
    return ""


@dataclass(frozen=True)
class FusionConfig(StageConfig):
    """Parameters of :class:`~hapticloud.core.fusion.SurfaceFusion`.

    Cross-field rules (:meth:`check`): each follower's gains must give a stable law (see the
    module docstring), ``max_extrapolation_s <= max_age_s`` and ``time_resolution_s < window_s``.
    """

    _path: ClassVar[str] = "fusion"

    # ----- regression -------------------------------------------------------------------------
    window_s: float = param(
        0.35, lo=0.02, hi=2.0, unit="s", doc="sliding window of estimates fitted (back from newest)"
    )
    weighting: str = param(
        "exponential",
        choices=_WEIGHTINGS,
        doc="age weights: exponential 0.5**(age/h) or inverse 1/(1 + age/h) (paper-like)",
    )
    weight_half_life_s: float = param(
        0.05, lo=0.005, hi=10.0, unit="s", log_scale=True, doc="age at which a sample weighs half"
    )
    max_degree: int = param(
        2, lo=0, hi=2, doc="polynomial degree in time (lowered with few samples)"
    )
    normal_max_degree: int = param(
        1, lo=0, hi=2, doc="polynomial degree of the normal (slower than the centroid: less noise)"
    )
    time_resolution_s: float = param(
        0.004,
        lo=1e-6,
        hi=0.05,
        unit="s",
        log_scale=True,
        doc="samples closer in time count as one time for the degree rule",
    )
    max_extrapolation_s: float = param(
        0.05,
        lo=0.0,
        hi=1.0,
        unit="s",
        doc="extrapolate at most this far past the newest; then hold",
    )
    max_age_s: float = param(
        0.3,
        lo=0.005,
        hi=5.0,
        unit="s",
        doc="no valid estimate for this long: stale, invalid (the tick holds, grown, from 0.1 s)",
    )
    max_samples: int = param(
        256, lo=4, hi=4096, gui=False, doc="cap on estimates kept in the window (oldest dropped)"
    )

    # ----- follower -----------------------------------------------------------------------------
    # Defaults: critically damped at 200 rad/s (centroid) and 100 rad/s (normal), with the
    # window's half-life 0.05 s: every shipped scene with cameras had set exactly these (sliding
    # scene: fused centroid 2.15 -> 1.14 mm median, normal 2.28 -> 1.25 deg, the largest normal
    # change between ticks 0.29 deg), and through a crease crossing they lag half as far as the
    # paper-like 50 / 30 rad/s (docs/benchmarks.md, "The fusion's defaults"). Softer gains pass
    # less of the 30 Hz jitter and lag more. ki = 0: with feed-forward the output has no
    # steady-state error left to integrate; the integral serves feedforward = 0 (the paper's pure
    # PID), where it removes the ramp lag kd * v / kp.
    feedforward: float = param(
        1.0,
        lo=0.0,
        hi=1.0,
        doc="fraction of the regression's own motion applied directly (0 = paper's pure PID)",
    )
    kp: float = param(
        40000.0,
        lo=0.0,
        hi=1e6,
        lo_open=True,
        unit="1/s²",
        log_scale=True,
        doc="centroid follower stiffness",
    )
    ki: float = param(0.0, lo=0.0, hi=1e8, unit="1/s³", doc="centroid follower integral gain")
    kd: float = param(
        400.0,
        lo=0.0,
        hi=1e4,
        lo_open=True,
        unit="1/s",
        log_scale=True,
        doc="centroid follower damping (on the output's rate)",
    )
    i_accel_limit_m_s2: float = param(
        5.0, lo=0.0, hi=1e3, unit="m/s²", doc="anti-windup: max acceleration from the integral"
    )
    normal_kp: float = param(
        10000.0,
        lo=0.0,
        hi=1e6,
        lo_open=True,
        unit="1/s²",
        log_scale=True,
        doc="normal follower stiffness",
    )
    normal_ki: float = param(0.0, lo=0.0, hi=1e8, unit="1/s³", doc="normal follower integral gain")
    normal_kd: float = param(
        200.0,
        lo=0.0,
        hi=1e4,
        lo_open=True,
        unit="1/s",
        log_scale=True,
        doc="normal follower damping (on the output's rate)",
    )
    normal_i_accel_limit_rad_s2: float = param(
        50.0, lo=0.0, hi=1e4, unit="rad/s²", doc="anti-windup: max angular accel. from the integral"
    )
    max_speed_m_s: float = param(
        2.0, lo=0.01, hi=50.0, unit="m/s", doc="output centroid moves at most this fast (per tick)"
    )
    max_normal_rate_rad_s: float = param(
        10.0,
        lo=0.01,
        hi=1000.0,
        unit="rad/s",
        log_scale=True,
        doc="output normal turns at most this fast (per-tick limit = rate * dt)",
    )
    reset_dt_s: float = param(
        0.1,
        lo=0.002,
        hi=10.0,
        unit="s",
        doc="a gap between samples longer than this resets followers",
    )

    # ----- cameras ----------------------------------------------------------------------------
    # With two or more cameras in the window each camera is also fitted on its own: the cameras
    # are weighted by the noise their estimates measured, and a camera whose surface lies farther
    # from the HIP than the nearest camera's by more than their noise explains (a calibration
    # error, a camera seeing another body) is left out: the nearer surface answers, never the
    # farther, and FusedSurface says so (disagree, disagreement_m, quality_note).
    weigh_cameras: bool = param(
        True,
        doc="fit each camera on its own: weight by measured residual, detect disagreement",
    )
    residual_floor_m: float = param(
        0.0005,
        lo=1e-6,
        hi=0.05,
        unit="m",
        log_scale=True,
        doc="a camera's fit residual counts as at least this (no camera is trusted without limit)",
    )
    disagreement_sigmas: float = param(
        3.0,
        lo=1.0,
        hi=20.0,
        doc="cameras disagree when their surfaces differ by more than this x their scatter",
    )
    disagreement_min_m: float = param(
        0.0015,
        lo=0.0,
        hi=0.05,
        unit="m",
        doc="and by more than this (m): smaller differences are never called disagreement",
    )

    def check(self) -> None:
        for prefix, (kp, ki, kd) in (
            ("", (self.kp, self.ki, self.kd)),
            ("normal_", (self.normal_kp, self.normal_ki, self.normal_kd)),
        ):
            problem = gain_problem(kp, ki, kd, prefix)
            if problem:
                raise ConfigError(f"unstable follower: {problem}")
        if self.max_extrapolation_s > self.max_age_s:
            raise ConfigError(
                f"max_extrapolation_s = {self.max_extrapolation_s}: must be <= max_age_s = "
                f"{self.max_age_s} (a held value cannot outlive staleness)"
            )
        if not self.time_resolution_s < self.window_s:
            raise ConfigError(
                f"time_resolution_s = {self.time_resolution_s}: "
                f"must be < window_s = {self.window_s}"
            )
