"""Least-squares fits of planes, 3D circles, spheres and local quadric patches to point sets.

Every fit centres the points on their (weighted) centroid and divides by their RMS spread before
any decomposition, so a point set 1e3 m from the origin gives the same answer as the same set near
it, and every decomposition works on numbers of order one. Normals come from the SVD of the
centred points; linear systems are solved on column-equilibrated designs by SVD-based least
squares or a QR factorisation (never normal equations). A degenerate input (too few points,
collinear or coplanar points, a straight arc, an ill-conditioned system) returns a result with
``valid=False`` and a ``reason``; its vectors are finite placeholders. NaN/inf rows are dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import lapack

from ..errors import InputError
from ..validation import as_points, as_vector3
from .rotations import rotation_between

FloatArray = NDArray[np.float64]

_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)
_EZ = np.array([0.0, 0.0, 1.0])
_EZ.setflags(write=False)

#: Default relative rank tolerance: singular value ratios below it count as rank loss.
RANK_TOL = 1e-6
#: Default largest condition number of an equilibrated least-squares design.
MAX_COND = 1e7
# Smallest 1 - dF/dz used in a height's derivative: guards vertical tangents (silhouettes).
_MIN_SLOPE_DEN = 0.25


def _frozen(value: Any, fallback: FloatArray = _ZERO3) -> FloatArray:
    arr = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        arr = np.array(fallback, dtype=np.float64)
    arr.setflags(write=False)
    return arr


def _finite_float(value: float, fallback: float = 0.0) -> float:
    value = float(value)
    return value if np.isfinite(value) else fallback


# ----- input preparation -------------------------------------------------------------------------


@dataclass(frozen=True)
class _Prepared:
    """Finite rows with positive weight, centred on ``centroid`` and divided by ``scale``."""

    centroid: FloatArray
    scale: float
    local: FloatArray  # (N, 3) (p - centroid) / scale
    weights: FloatArray  # (N,) normalised to mean 1
    n: int


def _as_weights(weights: ArrayLike | None, n_rows: int) -> FloatArray | None:
    if weights is None:
        return None
    w = np.asarray(weights)
    if w.dtype == object or not (
        np.issubdtype(w.dtype, np.floating) or np.issubdtype(w.dtype, np.integer)
    ):
        raise InputError(f"weights: expected real numbers, got dtype {w.dtype}")
    if w.shape != (n_rows,):
        raise InputError(f"weights: expected shape ({n_rows},) to match points, got {w.shape}")
    w = w.astype(np.float64)
    if np.any(w < 0.0):
        raise InputError("weights: must be non-negative")
    return w


def _prepare(points: ArrayLike, weights: ArrayLike | None) -> _Prepared | str:
    """Validate, drop unusable rows, centre and scale; a string says why nothing is left."""
    p = as_points(points, "points")
    w = _as_weights(weights, p.shape[0])
    keep = np.isfinite(p).all(axis=1)
    if w is not None:
        keep &= np.isfinite(w) & (w > 0.0)
    if not keep.all():
        p = p[keep]
        w = None if w is None else w[keep]
    n = p.shape[0]
    if n == 0:
        return "no finite points"
    if w is not None:
        w = w / w.max()  # first by the largest: the mean of huge weights would overflow
    w = np.ones(n) if w is None else w / w.mean()
    # Subtract a sample first: the mean of the differences keeps full precision far from 0.
    ref = p[0]
    d = p - ref
    mean = (w @ d) / n
    local = d - mean
    scale = float(np.sqrt((w @ np.einsum("ij,ij->i", local, local)) / n))
    if not np.isfinite(scale):
        return "coordinates too large to fit"
    if not scale > 0.0:
        return "all points coincide"
    return _Prepared(ref + mean, scale, local / scale, w, n)


def _weighted_svd(prep: _Prepared) -> tuple[FloatArray, FloatArray]:
    """Singular values and right singular vectors of the weighted, centred, scaled points."""
    _, sv, vt = np.linalg.svd(prep.local * np.sqrt(prep.weights)[:, None], full_matrices=False)
    return sv, vt


def _solve(design: FloatArray, rhs: FloatArray, sqrt_w: FloatArray) -> tuple[FloatArray, float]:
    """Weighted least squares via SVD on an equilibrated design; returns (solution, cond)."""
    a = design * sqrt_w[:, None]
    norms = np.sqrt(np.einsum("ij,ij->j", a, a))
    if not np.all(norms > 0.0):
        return np.full(design.shape[1], np.nan), np.inf
    a /= norms
    sol, _, rank, sv = np.linalg.lstsq(a, rhs * sqrt_w, rcond=None)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0.0 else np.inf
    if rank < design.shape[1]:
        cond = np.inf
    return sol / norms, cond


# ----- plane -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlaneFit:
    """A plane through ``centroid`` (m) with unit ``normal`` (sign arbitrary: orient it later).

    ``rms_m`` is the weighted RMS distance of the points to the plane.
    """

    valid: bool
    centroid: FloatArray
    normal: FloatArray
    rms_m: float
    reason: str = ""
    n_points: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "centroid", _frozen(self.centroid))
        object.__setattr__(self, "normal", _frozen(self.normal, _EZ))
        object.__setattr__(self, "rms_m", _finite_float(self.rms_m))


def _invalid_plane(reason: str, n: int = 0, centroid: FloatArray = _ZERO3) -> PlaneFit:
    return PlaneFit(False, centroid, _EZ, 0.0, reason, n)


def plane3d(
    points: ArrayLike, weights: ArrayLike | None = None, *, rank_tol: float = RANK_TOL
) -> PlaneFit:
    """Fit a plane by SVD of the centred points (total least squares).

    Parameters
    ----------
    points
        ``(N, 3)`` points (m). NaN/inf rows are dropped.
    weights
        Optional ``(N,)`` non-negative weights; rows with zero weight are ignored.
    rank_tol
        Points whose second singular value is below ``rank_tol`` times the first are collinear:
        no plane is defined.

    Returns
    -------
    PlaneFit
        ``valid=False`` with a reason for fewer than 3 points, coincident or collinear points.

    Examples
    --------
    >>> fit = plane3d([[0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]])
    >>> fit.valid, abs(float(fit.normal[2]))
    (True, 1.0)
    """
    prep = _prepare(points, weights)
    if isinstance(prep, str):
        return _invalid_plane(prep)
    if prep.n < 3:
        return _invalid_plane(f"plane needs 3 points, got {prep.n}", prep.n, prep.centroid)
    sv, vt = _weighted_svd(prep)
    if not sv[1] > rank_tol * sv[0]:
        return _invalid_plane("collinear points: plane undefined", prep.n, prep.centroid)
    normal = vt[2]
    dist = prep.local @ normal
    rms = prep.scale * float(np.sqrt((prep.weights @ (dist * dist)) / prep.n))
    return PlaneFit(True, prep.centroid, normal, rms, "", prep.n)


# ----- circle ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CircleFit:
    """A circle in 3D: ``center`` (m), unit ``normal`` of its plane (sign arbitrary), ``radius_m``.

    ``rms_m`` is the weighted RMS 3D distance of the points to the circle.
    """

    valid: bool
    center: FloatArray
    normal: FloatArray
    radius_m: float
    rms_m: float
    reason: str = ""
    n_points: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _frozen(self.center))
        object.__setattr__(self, "normal", _frozen(self.normal, _EZ))
        object.__setattr__(self, "radius_m", _finite_float(self.radius_m))
        object.__setattr__(self, "rms_m", _finite_float(self.rms_m))


def _invalid_circle(reason: str, n: int = 0, center: FloatArray = _ZERO3) -> CircleFit:
    return CircleFit(False, center, _EZ, 0.0, 0.0, reason, n)


def circle3d(
    points: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    rank_tol: float = RANK_TOL,
    max_radius_ratio: float = 100.0,
    max_cond: float = MAX_COND,
) -> CircleFit:
    """Fit a circle in 3D as in the paper (Alg. 2's ``circle3d``).

    The plane's normal is the last right singular vector of the centred, scaled points; a
    Rodrigues rotation takes that normal to ``z``; the centre and radius in the plane solve the
    linear (Kåsa) least-squares problem ``x² + y² = 2 a x + 2 b y + c``; the centre is rotated and
    shifted back.

    Parameters
    ----------
    points
        ``(N, 3)`` points (m). NaN/inf rows are dropped.
    weights
        Optional ``(N,)`` non-negative weights.
    rank_tol
        Relative singular-value threshold below which the points are collinear.
    max_radius_ratio
        A radius above this multiple of the points' RMS spread is a straight arc (a circle of
        infinite radius): flagged invalid instead of returning a centre far away.
    max_cond
        Largest accepted condition number of the (equilibrated) linear system.

    Returns
    -------
    CircleFit
        ``valid=False`` with a reason for fewer than 3 points, coincident or collinear points,
        a (near-)straight arc or an ill-conditioned system.
    """
    prep = _prepare(points, weights)
    if isinstance(prep, str):
        return _invalid_circle(prep)
    if prep.n < 3:
        return _invalid_circle(f"circle needs 3 points, got {prep.n}", prep.n, prep.centroid)
    sv, vt = _weighted_svd(prep)
    if not sv[1] > rank_tol * sv[0]:
        return _invalid_circle("collinear points: circle undefined", prep.n, prep.centroid)
    normal = vt[2]
    rot = rotation_between(normal, _EZ)
    uv = prep.local @ rot.T  # in-plane coordinates in columns 0, 1; out-of-plane in column 2
    x, y = uv[:, 0], uv[:, 1]
    design = np.column_stack((x, y, np.ones(prep.n)))
    sol, cond = _solve(design, x * x + y * y, np.sqrt(prep.weights))
    if not cond <= max_cond or not np.all(np.isfinite(sol)):
        return _invalid_circle("ill-conditioned circle fit (straight arc?)", prep.n, prep.centroid)
    a, b = 0.5 * sol[0], 0.5 * sol[1]
    r2 = sol[2] + a * a + b * b
    if not r2 > 0.0:
        return _invalid_circle("no real circle fits the points", prep.n, prep.centroid)
    radius = float(np.sqrt(r2))
    if radius > max_radius_ratio:  # local coordinates: the RMS spread is 1
        return _invalid_circle(
            f"straight arc: radius {radius * prep.scale:.3g} m > {max_radius_ratio:g} x spread",
            prep.n,
            prep.centroid,
        )
    radial = np.hypot(x - a, y - b) - radius
    d2 = radial * radial + uv[:, 2] * uv[:, 2]
    rms = prep.scale * float(np.sqrt((prep.weights @ d2) / prep.n))
    center = prep.centroid + prep.scale * (rot.T @ np.array([a, b, 0.0]))
    return CircleFit(True, center, normal, radius * prep.scale, rms, "", prep.n)


# ----- sphere ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SphereFit:
    """A sphere: ``center`` (m), ``radius_m``; ``rms_m`` is the weighted RMS distance to it."""

    valid: bool
    center: FloatArray
    radius_m: float
    rms_m: float
    reason: str = ""
    n_points: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _frozen(self.center))
        object.__setattr__(self, "radius_m", _finite_float(self.radius_m))
        object.__setattr__(self, "rms_m", _finite_float(self.rms_m))


def _invalid_sphere(reason: str, n: int = 0, center: FloatArray = _ZERO3) -> SphereFit:
    return SphereFit(False, center, 0.0, 0.0, reason, n)


def sphere3d(
    points: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    refine: bool = True,
    rank_tol: float = RANK_TOL,
    max_radius_ratio: float = 100.0,
    max_cond: float = MAX_COND,
) -> SphereFit:
    """Fit a sphere: algebraic least squares, then (optionally) geometric Gauss-Newton steps.

    The algebraic fit solves ``|x|² = 2 c . x + d`` on the centred, scaled points; ``refine``
    then minimises the sum of squared geometric distances ``(|x - c| - r)²`` (a few steps, each
    accepted only if it lowers the cost).

    Returns
    -------
    SphereFit
        ``valid=False`` with a reason for fewer than 4 points, coincident, collinear or coplanar
        points (a sphere through a circle is not unique), a radius above ``max_radius_ratio``
        times the RMS spread, or an ill-conditioned system.
    """
    prep = _prepare(points, weights)
    if isinstance(prep, str):
        return _invalid_sphere(prep)
    if prep.n < 4:
        return _invalid_sphere(f"sphere needs 4 points, got {prep.n}", prep.n, prep.centroid)
    sv, _ = _weighted_svd(prep)
    if not sv[2] > rank_tol * sv[0]:
        return _invalid_sphere("coplanar points: sphere undefined", prep.n, prep.centroid)
    q = prep.local
    sqrt_w = np.sqrt(prep.weights)
    design = np.column_stack((q, np.ones(prep.n)))
    sol, cond = _solve(design, np.einsum("ij,ij->i", q, q), sqrt_w)
    if not cond <= max_cond or not np.all(np.isfinite(sol)):
        return _invalid_sphere("ill-conditioned sphere fit", prep.n, prep.centroid)
    center = 0.5 * sol[:3]
    r2 = sol[3] + center @ center
    if not r2 > 0.0:
        return _invalid_sphere("no real sphere fits the points", prep.n, prep.centroid)
    radius = float(np.sqrt(r2))
    if refine and radius <= max_radius_ratio:
        center, radius = _refine_sphere(q, sqrt_w, center, radius)
    if not radius <= max_radius_ratio:
        return _invalid_sphere(
            f"flat patch: radius {radius * prep.scale:.3g} m > {max_radius_ratio:g} x spread",
            prep.n,
            prep.centroid,
        )
    dist = np.sqrt(np.einsum("ij,ij->i", q - center, q - center)) - radius
    rms = prep.scale * float(np.sqrt((prep.weights @ (dist * dist)) / prep.n))
    return SphereFit(
        True, prep.centroid + prep.scale * center, radius * prep.scale, rms, "", prep.n
    )


def _refine_sphere(
    q: FloatArray, sqrt_w: FloatArray, center: FloatArray, radius: float, steps: int = 5
) -> tuple[FloatArray, float]:
    def residual(c: FloatArray, r: float) -> tuple[FloatArray, FloatArray]:
        diff = q - c
        dist = np.sqrt(np.einsum("ij,ij->i", diff, diff))
        return dist - r, diff / np.maximum(dist, 1e-12)[:, None]

    res, unit = residual(center, radius)
    cost = float((sqrt_w * res) @ (sqrt_w * res))
    for _ in range(steps):
        jac = np.column_stack((-unit, -np.ones(len(q))))
        step, cond = _solve(jac, -res, sqrt_w)
        if not cond <= MAX_COND or not np.all(np.isfinite(step)):
            break
        new_c, new_r = center + step[:3], radius + float(step[3])
        new_res, new_unit = residual(new_c, new_r)
        new_cost = float((sqrt_w * new_res) @ (sqrt_w * new_res))
        if not new_cost < cost:
            break
        center, radius, res, unit, cost = new_c, new_r, new_res, new_unit, new_cost
        if float(step @ step) < 1e-20:
            break
    return center, abs(radius)


# ----- local quadric patch -----------------------------------------------------------------------

#: Models of :func:`quadric_patch`, simplest first, with the monomials each one uses.
QUADRIC_MODELS: dict[str, tuple[str, ...]] = {
    "plane": ("1", "x", "y"),
    "paraboloid": ("1", "x", "y", "xx", "xy", "yy"),
    "spheroid": ("1", "x", "y", "xx", "xy", "yy", "zz"),
    "quadric": ("1", "x", "y", "xx", "xy", "yy", "zz", "xz", "yz"),
}


def _monomial_rows(q: FloatArray, k: int, zhat: FloatArray | None = None) -> FloatArray:
    """``(k + 1, N)``: the first ``k`` of ``1, x, y, x², xy, y², z², xz, yz``, then ``z``.

    ``zhat`` stands for ``z`` inside the monomials (see :class:`NestedQuadricLSQ`).
    """
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    zm = z if zhat is None else zhat
    rows = np.empty((k + 1, len(q)))
    rows[k] = z
    products = ((x, x), (x, y), (y, y), (zm, zm), (x, zm), (y, zm))
    for i in range(k):
        if i == 0:
            rows[0] = 1.0
        elif i < 3:
            rows[i] = x if i == 1 else y
        else:
            u, v = products[i - 3]
            np.multiply(u, v, out=rows[i])
    return rows


def quadric_matrices(coef: ArrayLike) -> tuple[FloatArray, FloatArray, float]:
    """``(A, b, c)`` of ``F(q) = q^T A q + b . q + c`` for the coefficients of ``z = f(x, y, z)``.

    ``coef`` holds the coefficients of ``1, x, y, x², xy, y², z², xz, yz``; ``F = f - z``.
    """
    c0, cx, cy, cxx, cxy, cyy, czz, cxz, cyz = (float(v) for v in np.asarray(coef).reshape(9))
    a = np.array(
        [
            [cxx, 0.5 * cxy, 0.5 * cxz],
            [0.5 * cxy, cyy, 0.5 * cyz],
            [0.5 * cxz, 0.5 * cyz, czz],
        ]
    )
    return a, np.array([cx, cy, -1.0]), c0


def paraboloid_height(q: FloatArray, coef: FloatArray) -> FloatArray:
    """``c0 + cx x + cy y + cxx x² + cxy xy + cyy y²`` at local points ``q`` (local units)."""
    x, y = q[:, 0], q[:, 1]
    c = coef
    return c[0] + x * (c[1] + c[3] * x + c[4] * y) + y * (c[2] + c[5] * y)


def quadric_height(q: FloatArray, coef: FloatArray) -> FloatArray:
    """Height ``z`` of the surface ``z = f(x, y, z)`` above each local point's ``(x, y)``.

    The root of ``czz z² + (cxz x + cyz y - 1) z + P(x, y) = 0`` that continues the height field
    through the origin (the stable form ``2P / (1 - L + sqrt((1 - L)² - 4 czz P))``); where the
    vertical line misses the surface (past its silhouette) the discriminant is clipped at 0.
    """
    p = paraboloid_height(q, coef)
    one_minus_l = 1.0 - coef[7] * q[:, 0] - coef[8] * q[:, 1]
    disc = np.maximum(one_minus_l * one_minus_l - 4.0 * coef[6] * p, 0.0)
    den = one_minus_l + np.sqrt(disc)
    safe = np.abs(den) > 1e-12
    return np.where(safe, 2.0 * p / np.where(safe, den, 1.0), p)


class NestedQuadricLSQ:
    """Weighted least squares of ``z = f(x, y, z)`` for all nested models from one QR.

    Low-level (no validation): ``q`` is ``(N, 3)`` finite, already in the fit's frame and of order
    one; ``weights`` ``(N,)`` non-negative. The columns ``1, x, y | x², xy, y² | z² | xz, yz`` are
    weighted, equilibrated and factorised once together with ``z`` (``[A | z] = QR``). The leading
    ``k x k`` block of ``R`` and the first ``k`` entries of its last column solve the model made of
    the first ``k`` columns, and the squares of the remaining entries sum to that model's
    residual: every model of :data:`QUADRIC_MODELS` then costs a triangular solve, and comparing
    them (:meth:`rss`) costs nothing.

    ``response`` (optional, ``(N,)``) replaces ``z`` as the left-hand side (Gauss-Newton steps).
    ``zhat`` (optional, ``(N,)``) replaces the measured ``z`` inside the ``z²``, ``xz``, ``yz``
    columns by a smooth prediction of it (e.g. a paraboloid fitted first). With the measured
    ``z`` on both sides the fit can explain noise with itself: on flat data ``z (1 - c x) = 0``,
    a pair of planes, fits better than the plane. With a prediction the extra columns are
    (nearly) in the span of the quadratic ones on flat data, so the conditioning check rejects
    them, and on curved data they carry the fourth-order shape without errors-in-variables bias.
    """

    def __init__(
        self,
        q: FloatArray,
        weights: FloatArray,
        k_max: int = 9,
        zhat: FloatArray | None = None,
        response: FloatArray | None = None,
    ) -> None:
        n = len(q)
        k_max = min(k_max, max(n - 1, 0))
        aug = _monomial_rows(q, k_max, zhat)  # rows = columns of [A | z]: aug.T Fortran-ordered
        if response is not None:
            aug[k_max] = response
        aug *= np.sqrt(weights)
        norms = np.sqrt(np.einsum("ij,ij->i", aug, aug))
        norm_list = norms.tolist()
        usable = next((i for i in range(k_max) if not norm_list[i] > 0.0), k_max)
        self.usable = usable  # models stop at the first empty column
        self.norms = norms[:usable]
        self.r = np.zeros((1, 1))
        self._tail = np.zeros(1)
        if usable == 0 or not math.isfinite(norm_list[k_max]):
            self.usable = 0
            return
        if usable < k_max:
            aug = np.vstack((aug[:usable], aug[k_max:]))
        aug[:usable] *= (1.0 / self.norms)[:, None]
        # LAPACK's QR straight on the Fortran-ordered transpose: no copy, no Q formed. Only the
        # upper triangle of the leading block is read below (R); the rest holds reflectors.
        qr_packed, _, _, info = lapack.dgeqrf(aug.T, overwrite_a=True)
        r = qr_packed[: usable + 1]
        # A NaN anywhere reaches the last column's last entry (the response is reduced last).
        if info != 0 or not (math.isfinite(r[-1, -1]) and math.isfinite(r[0, 0])):
            self.usable = 0
            return
        self.r = r
        self._tail = r[:, -1] ** 2  # the last column lies on or above the diagonal

    def rss(self, model: str) -> float:
        """Weighted residual sum of squares of ``z`` for ``model`` (inf if it cannot be fitted)."""
        k = len(QUADRIC_MODELS[model])
        if k > self.usable or k >= self.r.shape[0]:
            return np.inf
        return float(self._tail[k:].sum())

    def solve(self, model: str, max_cond: float = MAX_COND) -> tuple[FloatArray | None, float]:
        """``(coef, cond)``: the 9 coefficients (unused ones 0), or None when ill-conditioned.

        ``cond`` is LAPACK's 1-norm estimate for the triangular factor (within a factor of the
        model's size of the 2-norm condition number of the equilibrated system).
        """
        k = len(QUADRIC_MODELS[model])
        if k > self.usable or k >= self.r.shape[0]:
            return None, np.inf
        rk = self.r[:k, :k]
        rcond, info = lapack.dtrcon(rk, norm="1", uplo="U")
        cond = 1.0 / rcond if info == 0 and rcond > 0.0 else np.inf
        if not cond <= max_cond:
            return None, cond
        sol, info = lapack.dtrtrs(rk, self.r[:k, -1])
        coef = np.zeros(9)
        coef[:k] = sol / self.norms[:k]
        return (coef, cond) if info == 0 and np.all(np.isfinite(coef)) else (None, cond)


def fit_local_quadric(
    q: FloatArray, weights: FloatArray, model: str, *, max_cond: float = MAX_COND
) -> tuple[FloatArray | None, float]:
    """One model of :class:`NestedQuadricLSQ`: ``(coef or None, cond)`` (local units)."""
    k = len(QUADRIC_MODELS[model])
    return NestedQuadricLSQ(q, weights, k).solve(model, max_cond)


def refine_quadric_heights(
    q: FloatArray, w: FloatArray, coef: FloatArray, model: str, iterations: int
) -> FloatArray:
    """Gauss-Newton on the heights ``z - H(x, y; θ)`` of a model with z-terms (local units).

    Low-level (no validation), for the coefficients ``coef`` of ``model`` first solved with a
    paraboloid's prediction of z in the z-terms: that prediction misses exactly the fourth-order
    shape those terms are there for. Here the model's own explicit height ``H`` (the root of the
    quadratic in z, :func:`quadric_height`) is fitted to the measured heights, each residual
    weighted by ``1 / (1 + |∇H|²)`` (vertical to normal distance, to first order):
    ``∂H/∂θ = m(x, y, H) / D`` with ``D = 1 - 2 czz H - cxz x - cyz y``, so a step is one weighted
    solve of the same nested structure. A step is kept only if it lowers the weighted squared
    residual. Exact on an exact model and free of errors-in-variables bias: no measured z is
    among the regressors.

    Returns
    -------
    numpy.ndarray
        The refined 9 coefficients (``coef`` itself if no step helped).
    """
    k = len(QUADRIC_MODELS[model])
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    quad = _monomial_rows(q, 6)[:6]  # 1, x, y, x², xy, y²: fixed, so built once
    basis = np.column_stack((np.ones(len(q)), x, y, z))  # last column: the heights below

    def geometric(c: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
        p = c[:6] @ quad
        lin = c[7] * x + c[8] * y if k > 7 else 0.0
        one_minus_l = 1.0 - lin
        root = one_minus_l + np.sqrt(np.maximum(one_minus_l * one_minus_l - 4.0 * c[6] * p, 0.0))
        height = 2.0 * p / np.where(np.abs(root) > 1e-12, root, 1.0)
        # Clipped: near a silhouette (vertical tangent) the height's derivative blows up.
        den = np.maximum(one_minus_l - 2.0 * c[6] * height, _MIN_SLOPE_DEN)
        basis[:, 3] = height
        slope = basis @ np.array(
            [[c[1], c[2]], [2.0 * c[3], c[4]], [c[4], 2.0 * c[5]], [c[7], c[8]]]
        )
        # Vertical -> normal distance, to first order: weight by 1 / (1 + |∇H|²).
        wg = w / (1.0 + np.einsum("ij,ij->i", slope, slope) / (den * den))
        r = z - height
        return height, den, wg, float(wg @ (r * r))

    height, den, wg, cost = geometric(coef)
    for _ in range(iterations):
        lsq = NestedQuadricLSQ(q, wg / (den * den), k, height, (z - height) * den)
        delta, _ = lsq.solve(model)
        if delta is None:
            break
        trial = coef + delta
        t_height, t_den, t_wg, t_cost = geometric(trial)
        if not t_cost < cost:
            break
        done = t_cost > cost * (1.0 - 1e-6)
        coef, height, den, wg, cost = trial, t_height, t_den, t_wg, t_cost
        if done:
            break
    return coef


def local_quadric_distance(q: FloatArray, coef: FloatArray) -> FloatArray:
    """Signed first-order (Sampson) distances ``-F / |∇F|`` of local points (local units).

    Positive on the ``+z`` side; exact for a plane, close to the geometric distance where the
    surface is smooth on the scale of the distance.
    """
    a, b, c = quadric_matrices(coef)
    grad = q @ (2.0 * a) + b
    # F = q.A.q + b.q + c = q.(grad + b) / 2 + c
    f_val = 0.5 * np.einsum("ij,ij->i", q, grad + b) + c
    gnorm = np.sqrt(np.einsum("ij,ij->i", grad, grad))
    return -f_val / np.maximum(gnorm, 1e-12)


def local_quadric_closest(coef: FloatArray, h: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """Closest point to ``h`` on the local quadric and the unit normal there (local units).

    The normal is ``-∇F / |∇F|`` (the ``+z`` side near the origin). ``None`` when no closest
    point is found (see :meth:`QuadricPatch.closest_point`).
    """
    c0, cx, cy, cxx, cxy, cyy, czz, cxz, cyz = (float(v) for v in coef)
    a = ((cxx, 0.5 * cxy, 0.5 * cxz), (0.5 * cxy, cyy, 0.5 * cyz), (0.5 * cxz, 0.5 * cyz, czz))
    b = (cx, cy, -1.0)
    found = _closest_on_quadric(a, b, c0, (float(h[0]), float(h[1]), float(h[2])))
    if found is None:
        return None
    q = found
    grad = [-(2.0 * (a[i][0] * q[0] + a[i][1] * q[1] + a[i][2] * q[2]) + b[i]) for i in range(3)]
    norm = math.sqrt(grad[0] ** 2 + grad[1] ** 2 + grad[2] ** 2)
    if not (norm > 0.0 and math.isfinite(norm)):
        return None
    return np.array(q), np.array(grad) / norm


def _sym_eigen(
    a: tuple[tuple[float, ...], ...],
) -> tuple[list[float], list[tuple[float, float, float]]]:
    """Eigenvalues and unit eigenvectors of a symmetric 3x3 matrix (tuples of floats).

    A matrix without ``z`` couplings (plane, paraboloid: third row zero) is diagonalised in
    closed form by one Jacobi rotation; anything else goes to LAPACK.
    """
    if a[0][2] == 0.0 and a[1][2] == 0.0 and a[2][2] == 0.0:
        p, r, s = a[0][0], a[0][1], a[1][1]
        theta = 0.5 * math.atan2(2.0 * r, p - s)
        cs, sn = math.cos(theta), math.sin(theta)
        mu1 = p * cs * cs + 2.0 * r * sn * cs + s * sn * sn
        mu2 = p * sn * sn - 2.0 * r * sn * cs + s * cs * cs
        return [mu1, mu2, 0.0], [(cs, sn, 0.0), (-sn, cs, 0.0), (0.0, 0.0, 1.0)]
    mu, vecs = np.linalg.eigh(np.array(a))
    cols = vecs.T.tolist()
    return mu.tolist(), [(v[0], v[1], v[2]) for v in cols]


def _closest_on_quadric(
    a: tuple[tuple[float, ...], ...],
    b: tuple[float, float, float],
    c: float,
    h: tuple[float, float, float],
    iters: int = 60,
) -> list[float] | None:
    """Closest point to ``h`` on ``q.A.q + b.q + c = 0`` (plain floats: 3-vectors are faster so)."""
    mu, vecs = _sym_eigen(a)
    eta = [v[0] * h[0] + v[1] * h[1] + v[2] * h[2] for v in vecs]
    beta = [v[0] * b[0] + v[1] * b[1] + v[2] * b[2] for v in vecs]
    tiny = 1e-12 * max(1.0, max(abs(m) for m in mu))
    lo = max([-0.5 / m for m in mu if m > tiny], default=-math.inf)
    hi = min([-0.5 / m for m in mu if m < -tiny], default=math.inf)

    def phi(lam: float) -> tuple[float, float, list[float]]:
        val, slope, p = c, 0.0, [0.0, 0.0, 0.0]
        for i in range(3):
            den = 1.0 + 2.0 * lam * mu[i]
            pi = (eta[i] - lam * beta[i]) / den
            g = 2.0 * mu[i] * pi + beta[i]
            val += (mu[i] * pi + beta[i]) * pi
            slope -= g * g / den
            p[i] = pi
        return val, slope, p

    lam = 0.0
    val, slope, p = phi(lam)
    # Keep a bracket [left, right] with phi(left) > 0 > phi(right): phi decreases on (lo, hi).
    left, right = (lam, hi) if val > 0.0 else (lo, lam)
    scale = 1.0 + max(abs(v) for v in eta)
    tol = 1e-13 * (abs(c) + scale)
    for _ in range(iters):
        if abs(val) <= tol:
            break
        new = lam - val / slope if slope < 0.0 else math.nan
        if not left < new < right:  # also catches NaN
            if math.isfinite(left) and math.isfinite(right):
                new = 0.5 * (left + right)
            elif math.isfinite(left):  # grow to the right until phi changes sign
                new = left + 2.0 * max(1.0, abs(left))
            else:
                new = right - 2.0 * max(1.0, abs(right))
        lam = new
        val, slope, p = phi(lam)
        if not math.isfinite(val):
            return None
        if val > 0.0:
            left = lam
        else:
            right = lam
        if right - left <= 1e-15 * (1.0 + abs(lam)):
            break
    if not abs(val) <= 1e-6 * scale:
        return None
    q = [vecs[0][i] * p[0] + vecs[1][i] * p[1] + vecs[2][i] * p[2] for i in range(3)]
    return q if all(math.isfinite(v) for v in q) else None


@dataclass(frozen=True)
class QuadricPatch:
    """A local surface ``z = f(x, y, z)`` in a frame at ``origin`` with axes ``frame`` (columns).

    The surface is the zero set of ``F(q) = q^T A q + b . q + c`` in scaled local coordinates
    ``q = frame^T (p - origin) / scale_m``, with ``b_z = -1``: a height field over the frame's
    ``x, y`` plane (``"plane"``, ``"paraboloid"``), optionally with a ``z²`` term (``"spheroid"``:
    exact for spheres and circular cylinders touching the origin's tangent plane) or ``z²``,
    ``xz``, ``yz`` terms (``"quadric"``: any quadric). Because ``|∇F| ≈ 1`` near the origin, the
    algebraic residual is close to the geometric one there.

    ``coef`` holds the coefficients of ``1, x, y, x², xy, y², z², xz, yz`` (unused ones 0);
    ``rms_m`` is the weighted RMS residual (m) and ``cond`` the condition number of the fit.
    """

    valid: bool
    origin: FloatArray
    frame: FloatArray
    scale_m: float
    model: str
    coef: FloatArray
    rms_m: float
    cond: float
    n_points: int = 0
    reason: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin", _frozen(self.origin))
        object.__setattr__(self, "frame", _frozen(self.frame, np.eye(3)))
        object.__setattr__(self, "coef", _frozen(self.coef, np.zeros(9)))
        object.__setattr__(self, "rms_m", _finite_float(self.rms_m))

    @property
    def n_params(self) -> int:
        """Number of fitted coefficients."""
        return len(QUADRIC_MODELS.get(self.model, ()))

    def to_local(self, points: ArrayLike) -> FloatArray:
        """Scaled local coordinates ``(N, 3)`` of world ``points``."""
        p = as_points(points, "points")
        return ((p - self.origin) @ self.frame) / self.scale_m

    def residuals(self, points: ArrayLike) -> FloatArray:
        """Signed distances (m) of ``points`` to the surface, positive on the ``+z`` side."""
        return self.scale_m * local_quadric_distance(self.to_local(points), self.coef)

    def closest_point(self, point: ArrayLike) -> tuple[bool, FloatArray, FloatArray]:
        """The surface point closest to ``point`` and the unit normal there (world, m).

        Solves the Lagrange conditions ``q - h + λ ∇F(q) = 0``, ``F(q) = 0`` through the secular
        equation in the eigenbasis of ``A``, on the interval where ``I + 2 λ A`` is positive
        definite: there the equation is monotone, its root unique and the global minimiser
        (safeguarded Newton with bisection). ``ok=False`` (with the frame's origin and axis) when
        the patch is invalid, no such root exists or the iteration fails.
        """
        h = self.to_local(np.reshape(as_vector3(point, "point"), (1, 3)))[0]
        found = local_quadric_closest(self.coef, h) if self.valid else None
        if found is None:
            return False, self.origin.copy(), self.frame[:, 2].copy()
        q, n = found
        return True, self.origin + self.scale_m * (self.frame @ q), self.frame @ n


def quadric_patch(
    points: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    origin: ArrayLike,
    normal: ArrayLike,
    model: str = "paraboloid",
    scale_m: float | None = None,
    max_cond: float = MAX_COND,
    refine_steps: int = 5,
) -> QuadricPatch:
    """Fit a local surface ``z = f(x, y, z)`` in a frame at ``origin``, ``z`` along ``normal``.

    Parameters
    ----------
    points
        ``(N, 3)`` points (m); NaN/inf rows dropped.
    weights
        Optional ``(N,)`` non-negative weights (robust x spatial, chosen by the caller).
    origin
        Frame origin (m), e.g. the current closest-point estimate.
    normal
        Frame ``z`` axis (any length), e.g. the current normal estimate.
    model
        One of :data:`QUADRIC_MODELS`: ``"plane"``, ``"paraboloid"``, ``"spheroid"``, ``"quadric"``.
    scale_m
        Length that divides the local coordinates (m); default the points' RMS distance to the
        origin. Choose the neighbourhood's size: the coefficients are then of order one.
    max_cond
        Largest accepted condition number of the equilibrated system.
    refine_steps
        Gauss-Newton steps for the z-terms of ``"spheroid"`` and ``"quadric"``
        (:func:`refine_quadric_heights`).

    Returns
    -------
    QuadricPatch
        ``valid=False`` with a reason for too few points (the model's coefficients plus one),
        points all at the origin or an ill-conditioned system.

    Raises
    ------
    InputError
        For a wrong shape/dtype (naming the argument) or an unknown ``model``.
    """
    if model not in QUADRIC_MODELS:
        raise InputError(f"model = {model!r}: must be one of {', '.join(QUADRIC_MODELS)}")
    o = as_vector3(origin, "origin")
    frame = rotation_between(_EZ, as_vector3(normal, "normal"))
    p = as_points(points, "points")
    w = _as_weights(weights, p.shape[0])
    keep = np.isfinite(p).all(axis=1)
    if w is not None:
        keep &= np.isfinite(w) & (w > 0.0)
    p = p[keep]
    w = np.ones(len(p)) if w is None else w[keep]
    n = len(p)

    def invalid(reason: str, scale: float = 1.0, cond: float = np.inf) -> QuadricPatch:
        return QuadricPatch(False, o, frame, scale, model, np.zeros(9), 0.0, cond, n, reason)

    n_coef = len(QUADRIC_MODELS[model])
    if n < n_coef + 1:
        return invalid(f"{model} needs {n_coef + 1} points, got {n}")
    local = (p - o) @ frame
    if scale_m is None:
        scale = float(np.sqrt(np.mean(np.einsum("ij,ij->i", local, local))))
    else:
        scale = float(scale_m)
    if not (np.isfinite(scale) and scale > 0.0):
        return invalid("all points at the origin: no scale")
    q = local / scale
    wn = w / w.mean()
    k = len(QUADRIC_MODELS[model])
    lsq = NestedQuadricLSQ(q, wn, min(k, 6))
    coef, cond = lsq.solve(model if k <= 6 else "paraboloid", max_cond)
    if coef is not None and k > 6:
        # z-terms: a paraboloid's prediction of z first, then the model's own heights.
        coef, cond = NestedQuadricLSQ(q, wn, k, paraboloid_height(q, coef)).solve(model, max_cond)
        if coef is not None:
            coef = refine_quadric_heights(q, wn, coef, model, refine_steps)
    if coef is None:
        return invalid(f"ill-conditioned {model} fit (cond {cond:.3g})", scale, cond)
    res = local_quadric_distance(q, coef)
    rms = scale * float(np.sqrt((wn @ (res * res)) / n))
    return QuadricPatch(True, o, frame, scale, model, coef, rms, cond, n)
