"""Fusion: merge every camera's 30 Hz surface estimates into one smooth surface at 800 Hz.

Weighted quadratic regression over a sliding window (:mod:`.regression`), then PID followers
(:mod:`.follower`); :class:`SurfaceFusion` ties them together with staleness handling.
"""

from .config import FusionConfig, gain_problem
from .follower import NormalFollower, PidGains, PointFollower, iteration_matrix
from .fusion import CameraAgreement, FusedSurface, SurfaceFusion
from .regression import PolyFit, fit_window

__all__ = [
    "CameraAgreement",
    "FusedSurface",
    "FusionConfig",
    "NormalFollower",
    "PidGains",
    "PointFollower",
    "PolyFit",
    "SurfaceFusion",
    "fit_window",
    "gain_problem",
    "iteration_matrix",
]
