"""Weighted polynomial regression of the surface over a sliding time window (paper IV-F, eqs. 3-5).

Every estimate in the window (all cameras) is one row, weighted by its age (:func:`age_weights`:
exponential or the paper's inverse age, tapered to zero at the window's edge). Time is centred
on the newest sample and scaled by the window, ``tau = (t - t_newest) / window_s`` in
``[-1, 0]``, so epoch timestamps (1.7e9 s) condition the fit exactly like times near zero. Each
coordinate is fitted with ``x(tau) = a0 + a1 tau + a2 tau²`` by weighted least squares (``lstsq``
on ``sqrt(W) A``, never normal equations); the degree drops with the number of distinct sample
times (1 -> constant, 2 -> linear) and again whenever the weighted design is rank-deficient. The
normal has its own maximum degree (it turns slower than the centroid moves; a lower degree is
less noisy).

Normal without singularities
----------------------------
The paper filters two spherical angles, which has a pole (azimuth undefined at ±z) and a wrap
(azimuth jumps by 2π across -x). Here each normal is mapped into the tangent plane of a reference
normal ``r`` with the sphere's log map, ``v = θ (n - (n·r) r) / |n - (n·r) r|`` with
``θ = angle(n, r)``, the three components of ``v`` are regressed like the centroid, and the value
is mapped back with the exp map ``n = cos|v| r + sin|v| v/|v|``. The reference is the newest
estimate's normal: it depends on the data only (not on the follower's history), it keeps every
window normal far from the map's only singular point (the antipode of ``r``), and it makes the
fit rotation-equivariant (rotating all inputs rotates the output). Working with the 3D tangent
vector needs no tangent basis, so there is no frame choice that could itself have a singularity.
A normal exactly antipodal to ``r`` (a different surface, seen within one window) is mapped to
``θ = π`` along a fixed perpendicular: finite and deterministic, it enters the fit as the outlier
it is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
Vec3 = tuple[float, float, float]

_RANK_RTOL = 1e-9  # singular value ratio below which a weighted design counts as rank-deficient


def age_weights(
    age_s: FloatArray, half_life_s: float, window_s: float, kind: str = "exponential"
) -> FloatArray:
    """Weights falling with age (s): ``0.5 ** (age/h)`` or ``1 / (1 + age/h)``, tapered.

    Both are 1 at age 0 and 0.5 at ``age = half_life_s`` before the taper; ``inverse`` is the
    paper's "inverse proportional to arrival age" with the +1 guarding age 0. The taper
    ``1 - (age/window)²`` brings every weight to 0 at the window's edge, so a sample leaving the
    window changes the fit continuously (no target jump when an old estimate drops out, and an
    epoch timestamp rounded across the edge changes nothing). Positive for ``0 <= age < window``.
    """
    x = np.maximum(age_s, 0.0) / half_life_s
    base = 1.0 / (1.0 + x) if kind == "inverse" else np.exp2(-x)
    edge = np.minimum(age_s / window_s, 1.0)
    return base * (1.0 - edge * edge)


def count_distinct_times(times: FloatArray, resolution_s: float) -> int:
    """Number of groups of ``times`` separated by gaps larger than ``resolution_s``."""
    if times.size == 0:
        return 0
    ordered = np.sort(times)
    return 1 + int(np.count_nonzero((ordered[1:] - ordered[:-1]) > resolution_s))


def perpendicular(v: Vec3) -> Vec3:
    """A unit vector perpendicular to unit ``v``, chosen deterministically."""
    x, y, z = v
    # Cross with the world axis least aligned with v: never near-parallel.
    ax, ay, az = abs(x), abs(y), abs(z)
    if ax <= ay and ax <= az:
        p = (0.0, -z, y)
    elif ay <= az:
        p = (z, 0.0, -x)
    else:
        p = (-y, x, 0.0)
    norm = math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
    return (p[0] / norm, p[1] / norm, p[2] / norm)


def log_map(ref: Vec3, normals: FloatArray) -> FloatArray:
    """Tangent vectors at unit ``ref`` of unit ``normals (N, 3)``; ``|v|`` is the angle (rad)."""
    r = np.asarray(ref, dtype=np.float64)
    cos = normals @ r
    u = normals - cos[:, None] * r
    sin = np.sqrt((u * u).sum(axis=1))
    tiny = sin < 1e-12
    if tiny.any():
        # theta/sin -> 1 as the angle -> 0: v = u (tiny) there; the antipode gets a fixed tangent.
        factor = np.where(tiny, 1.0, np.arctan2(sin, cos) / np.where(tiny, 1.0, sin))
        v = u * factor[:, None]
        v[tiny & (cos < 0.0)] = math.pi * np.asarray(perpendicular(ref))
        return v
    return u * (np.arctan2(sin, cos) / sin)[:, None]


def exp_map(ref: Vec3, v: Vec3) -> Vec3:
    """Unit normal reached from unit ``ref`` along tangent ``v`` (its part along ``ref`` dropped).

    The angle is capped at π (beyond it the map would wrap round to the other side).
    """
    rx, ry, rz = ref
    vx, vy, vz = v
    d = vx * rx + vy * ry + vz * rz
    vx, vy, vz = vx - d * rx, vy - d * ry, vz - d * rz
    phi = math.sqrt(vx * vx + vy * vy + vz * vz)
    if phi > math.pi:
        s = math.pi / phi
        vx, vy, vz, phi = vx * s, vy * s, vz * s, math.pi
    c = math.cos(phi)
    sinc = math.sin(phi) / phi if phi > 1e-8 else 1.0 - phi * phi / 6.0
    nx, ny, nz = c * rx + sinc * vx, c * ry + sinc * vy, c * rz + sinc * vz
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    if not norm > 1e-12:  # unreachable for unit ref (|n| = 1); kept so a bad ref never gives NaN
        return ref
    return (nx / norm, ny / norm, nz / norm)


@dataclass(frozen=True, slots=True)
class PolyFit:
    """Polynomials of the window, in scaled time ``tau = (t - t_ref) / scale_s``.

    ``coeffs[j] = (a0, a1, a2)`` for column ``j`` of ``(cx, cy, cz, vx, vy, vz)``: centroid (m)
    and the normal's tangent vector at ``ref_normal`` (rad). Higher coefficients than ``degree``
    are zero; ``degree`` is the centroid's, ``normal_degree`` the normal's. ``valid`` is False
    (with ``reason``) if the fit could not be made finite.
    """

    t_ref: float
    scale_s: float
    coeffs: tuple[tuple[float, float, float], ...]
    ref_normal: Vec3
    degree: int
    n_samples: int
    n_times: int
    cameras: tuple[str, ...]
    normal_degree: int = 0
    valid: bool = True
    reason: str = ""

    def evaluate(self, t: float) -> tuple[Vec3, Vec3, Vec3]:
        """Centroid (m), unit normal and centroid velocity (m/s) at time ``t`` (s)."""
        scale = self.scale_s
        tau = (t - self.t_ref) / scale
        # Unrolled (it runs every control tick); the normal's rates are not needed.
        (c0, c1, c2), (d0, d1, d2), (e0, e1, e2), (f0, f1, f2), (g0, g1, g2), (k0, k1, k2) = (
            self.coeffs
        )
        normal = exp_map(
            self.ref_normal,
            (f0 + tau * (f1 + tau * f2), g0 + tau * (g1 + tau * g2), k0 + tau * (k1 + tau * k2)),
        )
        return (
            (c0 + tau * (c1 + tau * c2), d0 + tau * (d1 + tau * d2), e0 + tau * (e1 + tau * e2)),
            normal,
            (
                (c1 + 2.0 * tau * c2) / scale,
                (d1 + 2.0 * tau * d2) / scale,
                (e1 + 2.0 * tau * e2) / scale,
            ),
        )


def fit_window(
    times: FloatArray,
    centroids: FloatArray,
    normals: FloatArray,
    cameras: Sequence[str],
    *,
    window_s: float,
    half_life_s: float,
    weighting: str = "exponential",
    max_degree: int = 2,
    normal_max_degree: int = 2,
    time_resolution_s: float = 1e-3,
    sample_weights: FloatArray | None = None,
) -> PolyFit:
    """Fit the samples ``times (N,)`` s, ``centroids (N, 3)`` m, unit ``normals (N, 3)``.

    The caller has already kept only the window (ages ``< window_s`` from the newest); ``N >= 1``.
    The newest sample (the last one given among equal newest times) supplies the reference normal.
    ``sample_weights (N,)`` (positive) multiply the age weights (a camera's trust); ``None``
    weighs by age alone.
    """
    newest = newest_index(times)
    w = age_weights(times[newest] - times, half_life_s, window_s, weighting)
    if sample_weights is not None:
        w = w * sample_weights
    return fit_weighted(
        times,
        centroids,
        normals,
        cameras,
        newest,
        w,
        count_distinct_times(times, time_resolution_s),
        window_s=window_s,
        max_degree=max_degree,
        normal_max_degree=normal_max_degree,
    )


def newest_index(times: FloatArray) -> int:
    """Index of the newest sample: the last one given among equal newest times."""
    return int(times.shape[0]) - 1 - int(np.argmax(times[::-1]))


def fit_weighted(
    times: FloatArray,
    centroids: FloatArray,
    normals: FloatArray,
    cameras: Sequence[str],
    newest: int,
    weights: FloatArray,
    n_times: int,
    *,
    window_s: float,
    max_degree: int = 2,
    normal_max_degree: int = 2,
) -> PolyFit:
    """:func:`fit_window` with its weights and counts already known.

    ``newest`` is :func:`newest_index` of ``times``, ``weights (N,)`` the age weights (times
    any sample weights) and ``n_times`` :func:`count_distinct_times`: a caller that has them
    (the fusion's camera comparison) does not compute them twice.
    """
    n = int(times.shape[0])
    t_ref = float(times[newest])
    ref = tuple(normals[newest].tolist())
    age = t_ref - times
    sw = np.sqrt(weights)  # sqrt(W) A: W-norm LS
    # Fit offsets from the newest centroid: large world coordinates lose no digits in the solve.
    origin = centroids[newest]
    Yw = np.empty((n, 6))
    Yw[:, :3] = centroids - origin
    Yw[:, 3:] = log_map(ref, normals)
    Yw *= sw[:, None]
    cams = tuple(sorted(set(cameras)))
    # Rows of sqrt(W) [1, tau, tau²], tau = -age / window in [-1, 0].
    A = np.empty((n, 3))
    A[:, 0] = sw
    A[:, 1] = sw * (-age / window_s)
    A[:, 2] = A[:, 1] * (-age / window_s)
    full = np.zeros((3, 6))
    degree = min(max_degree, n_times - 1)
    normal_degree = min(normal_max_degree, n_times - 1)
    if degree == normal_degree:
        degree = normal_degree = _solve(A, Yw, degree, full)
    else:
        degree = _solve(A, Yw[:, :3], degree, full[:, :3])
        normal_degree = _solve(A, Yw[:, 3:], normal_degree, full[:, 3:])
    if not np.isfinite(full).all():
        return PolyFit(
            t_ref,
            window_s,
            ((0.0, 0.0, 0.0),) * 6,
            ref,
            0,
            n,
            n_times,
            cams,
            valid=False,
            reason="regression failed (non-finite coefficients)",
        )
    full[0, :3] += origin
    coeffs = tuple(map(tuple, full.T.tolist()))
    return PolyFit(t_ref, window_s, coeffs, ref, degree, n, n_times, cams, normal_degree)


def _solve(A: FloatArray, Yw: FloatArray, degree: int, out: FloatArray) -> int:
    """Least squares of ``Yw`` on the first ``degree + 1`` columns of ``A`` into ``out``.

    Falls back a degree while the design is rank-deficient; degree 0 always has rank 1 because
    every weight is positive. Returns the degree used.
    """
    while degree > 0:
        coef, _, rank, sv = np.linalg.lstsq(A[:, : degree + 1], Yw, rcond=None)
        if rank == degree + 1 and sv[-1] > _RANK_RTOL * sv[0]:
            out[: degree + 1] = coef
            return degree
        degree -= 1
    out[0] = np.linalg.lstsq(A[:, :1], Yw, rcond=None)[0][0]
    return 0
