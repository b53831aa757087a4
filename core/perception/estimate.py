"""What the perception pipeline hands on: one surface estimate per camera frame."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..haptics.distance import d_proj

FloatArray = NDArray[np.float64]

_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)
_UP = np.array([0.0, 0.0, 1.0])
_UP.setflags(write=False)


def _frozen_vec3(value: Any) -> tuple[FloatArray, bool]:
    arr = np.array(value, dtype=np.float64).reshape(-1)
    ok = arr.shape == (3,) and bool(np.all(np.isfinite(arr)))
    arr.setflags(write=False)
    return arr, ok


def _frozen_points(value: Any) -> FloatArray:
    arr = np.array(value, dtype=np.float64).reshape(-1, 3)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class ShellFit:
    """The fit of one concentric shell ``r_inner_m < |p - hip| < r_outer_m`` (Alg. 2).

    ``kind`` is ``"plane"`` (first non-empty shell) or ``"circle"``; ``radius_m`` is the fitted
    circle's radius (0 for a plane). ``kept`` is False when the estimate was among the rejected
    worst half; ``valid`` is False when the fit was degenerate (then it is never used).
    """

    r_inner_m: float
    r_outer_m: float
    kind: str
    center: FloatArray
    normal: FloatArray
    n_points: int
    valid: bool
    kept: bool = False
    radius_m: float = 0.0

    def __post_init__(self) -> None:
        center, ok_c = _frozen_vec3(self.center)
        normal, ok_n = _frozen_vec3(self.normal)
        object.__setattr__(self, "center", center if ok_c else _ZERO3)
        object.__setattr__(self, "normal", normal if ok_n else _UP)
        if not (ok_c and ok_n):
            object.__setattr__(self, "valid", False)
            object.__setattr__(self, "kept", False)


@dataclass(frozen=True)
class SurfaceEstimate:
    """The surface point closest to the HIP, and its normal, seen by one camera at time ``t``.

    ``centroid`` (world frame, m) and ``normal`` (unit, pointing out of the surface towards the
    HIP/camera side) are finite whatever happens; when ``valid`` is False they are placeholders
    and ``reason`` says why. Constructible from ``t, camera, centroid, normal, valid`` alone; the
    rest is what the app shows (per-shell fits, kept points, stage timings).
    """

    t: float
    camera: str
    centroid: FloatArray
    normal: FloatArray
    valid: bool
    reason: str = ""
    method: str = ""
    quality: float = 0.0
    hip: FloatArray | None = None
    n_points: int = 0
    shells: tuple[ShellFit, ...] = ()
    points: FloatArray | None = None
    filled: FloatArray | None = None
    stage_ms: Mapping[str, float] = field(default_factory=dict)
    #: Points of the clusters stage C rejected (``keep_points`` only; world, m).
    rejected: FloatArray | None = None
    seq: int = 0
    #: An invalid estimate that proves free space: no surface within this distance of ``hip``
    #: (m; the workspace radius when the frame saw the whole workspace empty), else 0.
    free_m: float = 0.0
    #: Surfaces the points held near the HIP: 2 at a crease or where two bodies touch (the
    #: estimate is then the nearer one, never a blend); ``note`` says which, on a valid estimate.
    surfaces: int = 1
    note: str = ""
    #: The surface fit's residual scale (m): the measured noise of the points this estimate
    #: stands on; the fusion weights cameras by it. 0 when unknown (not measured, or not sent).
    residual_m: float = 0.0

    def __post_init__(self) -> None:
        centroid, ok_c = _frozen_vec3(self.centroid)
        normal, ok_n = _frozen_vec3(self.normal)
        norm = float(np.linalg.norm(normal)) if ok_n else 0.0
        ok_n = ok_n and norm > 1e-9
        if ok_n:
            normal = normal / norm
            normal.setflags(write=False)
        object.__setattr__(self, "centroid", centroid if ok_c else _ZERO3)
        object.__setattr__(self, "normal", normal if ok_n else _UP)
        if not (ok_c and ok_n) and self.valid:
            object.__setattr__(self, "valid", False)
            object.__setattr__(self, "reason", self.reason or "non-finite centroid or normal")
        object.__setattr__(self, "t", float(self.t))
        res = float(self.residual_m)
        object.__setattr__(self, "residual_m", res if 0.0 < res < math.inf else 0.0)
        free = float(self.free_m)
        object.__setattr__(
            self, "free_m", free if 0.0 < free < math.inf and not self.valid else 0.0
        )
        if self.hip is not None:
            object.__setattr__(self, "hip", _frozen_vec3(self.hip)[0])
        for name in ("points", "filled", "rejected"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _frozen_points(value))
        object.__setattr__(self, "stage_ms", MappingProxyType(dict(self.stage_ms)))

    def d_proj(self, hip: NDArray, r_hip_m: float) -> float:
        """Signed free distance ``(c - h) . (-n) - r_hip`` (m); negative means penetration."""
        return d_proj(self.centroid, self.normal, hip, r_hip_m)

    @classmethod
    def invalid(cls, t: float, camera: str, reason: str, **extra: Any) -> SurfaceEstimate:
        """An estimate flagged invalid with ``reason`` (finite placeholder vectors)."""
        return cls(
            t=t, camera=camera, centroid=_ZERO3, normal=_UP, valid=False, reason=reason, **extra
        )
