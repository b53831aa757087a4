"""The naive baseline: the cloud's nearest point to the HIP and a plane through its neighbours.

Kept to measure the other estimators against. It is biased by construction: the minimum of noisy
distances reports the surface too close, and when the end effector hides the true closest point
the nearest visible point sits on the rim of the hidden region.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from ..geometry.fits import plane3d
from ..geometry.rotations import orient_normal
from ..validation import as_points, as_unit_vector3, as_vector3, drop_nonfinite
from .abstraction import SurfaceFit


def nearest_point(
    points: ArrayLike, hip: ArrayLike, camera_axis: ArrayLike, k: int = 20
) -> SurfaceFit:
    """Nearest point to ``hip`` as the centroid; the normal of a plane through its ``k`` neighbours.

    Parameters
    ----------
    points
        ``(N, 3)`` points (m, world); NaN/inf rows dropped.
    hip
        HIP position (m).
    camera_axis
        Viewing direction; the normal is turned to face the camera.
    k
        Neighbours (including the nearest point itself) for the plane fit, at least 3.

    Returns
    -------
    SurfaceFit
        ``valid=False`` for fewer than 3 points or collinear neighbours.
    """
    pts = drop_nonfinite(as_points(points, "points"))
    h = as_vector3(hip, "hip")
    z = as_unit_vector3(camera_axis, "camera_axis")
    n = len(pts)
    if n < 3:
        return SurfaceFit.invalid(f"nearest needs 3 points, got {n}", method="nearest", n_points=n)
    rel = pts - h
    nearest = int(np.argmin(np.einsum("ij,ij->i", rel, rel)))
    centroid = pts[nearest]
    k = int(min(max(k, 3), n))
    around = pts - centroid
    d2 = np.einsum("ij,ij->i", around, around)
    idx = np.argpartition(d2, k - 1)[:k] if k < n else np.arange(n)
    fit = plane3d(pts[idx])
    if not fit.valid:
        return SurfaceFit.invalid(
            f"neighbour plane: {fit.reason}", method="nearest", model="plane", n_points=n
        )
    normal = orient_normal(fit.normal, z, centroid, h)
    spread = float(np.sqrt(d2[idx].max()))
    # Flat neighbourhoods (rms small against their size) give trustworthy normals.
    quality = 1.0 / (1.0 + 10.0 * fit.rms_m / spread) if spread > 0.0 else 0.0
    return SurfaceFit(
        True, centroid, normal, "", (), quality, "nearest", "plane", n, residual_m=fit.rms_m
    )
