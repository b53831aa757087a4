"""Least-squares fits of planes, 3D circles and spheres to point sets (quadrics: :mod:`.quadric`).

Every fit centres the points on their (weighted) centroid and divides by their RMS spread before
any decomposition, so a point set 1e3 m from the origin gives the same answer as the same set near
it, and every decomposition works on numbers of order one. Normals come from the SVD of the
centred points; linear systems are solved on column-equilibrated designs by SVD-based least
squares or a QR factorisation (never normal equations). A degenerate input (too few points,
collinear or coplanar points, a straight arc, an ill-conditioned system) returns a result with
``valid=False`` and a ``reason``; its vectors are finite placeholders. NaN/inf rows are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from ._lsq import (
    _EZ,
    _ZERO3,
    MAX_COND,
    RANK_TOL,
    FloatArray,
    _finite_float,
    _frozen,
    _prepare,
    _solve,
    _weighted_svd,
)
from .rotations import rotation_between

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
