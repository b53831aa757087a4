"""Closed-form ray intersections with convex solids, vectorised over rays.

Every function takes ``origins`` ``(M, 3)`` (or one ``(3,)`` origin for all rays) and
``directions`` ``(M, 3)`` (need not be unit: ``t`` is in units of the direction's length, so a
camera ray ``(x/z, y/z, 1)`` rotated to the world gives the depth ``z`` directly) and returns
``(t, normals)``: the smallest ``t > 0`` where the ray meets the surface (``inf`` on a miss) and the
outward unit normal there (zeros on a miss).

Taking the smallest positive root over all pieces of a solid's surface (sphere caps, side,
planes) is exact for a ray starting outside a convex solid: every root that is not on the surface
lies inside the solid, hence behind the entry point. Rays starting inside a solid get its exit.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

_T_MIN = 1e-9  # m: roots at the origin itself are not hits


def _rows_dot(a: FloatArray, b: FloatArray) -> FloatArray | float:
    """Row-wise dot products; a single (3,) operand (the common ray origin) is not broadcast."""
    if a.ndim == 1 and b.ndim == 1:
        return float(a @ b)
    if a.ndim == 1:
        return b @ a
    if b.ndim == 1:
        return a @ b
    return np.einsum("ij,ij->i", a, b)


def _rows(x: FloatArray, mask: NDArray[np.bool_]) -> FloatArray:
    return x if x.ndim == 1 else x[mask]


def _prepare(origins: NDArray, directions: NDArray) -> tuple[FloatArray, FloatArray]:
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    o = np.asarray(origins, dtype=np.float64)
    if o.shape != (3,):
        o = np.broadcast_to(o, d.shape)
    return o, d


def _quadratic_roots(
    a: FloatArray, half_b: FloatArray, c: FloatArray | float
) -> tuple[FloatArray, FloatArray]:
    """Roots of ``a t^2 + 2 half_b t + c`` (NaN where none), cancellation-free."""
    disc = half_b * half_b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(disc)
        q = -(half_b + np.copysign(sq, half_b))
        t1 = q / a
        t2 = c / q
    bad = ~(disc >= 0) | ~(a > 0)
    t1[bad] = np.nan
    t2[bad] = np.nan
    return t1, t2


def _positive(t: FloatArray) -> FloatArray:
    return np.where(t > _T_MIN, t, np.inf)  # NaN compares False: becomes inf too


def _take_min(best_t: FloatArray, best_n: FloatArray, t: FloatArray, n: FloatArray) -> None:
    closer = t < best_t
    best_t[closer] = t[closer]
    best_n[closer] = n[closer]


def _unit_rows(v: FloatArray) -> FloatArray:
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, norm, out=np.zeros_like(v), where=norm > 0)


def _sphere(
    o: FloatArray, d: FloatArray, dd: FloatArray, center: FloatArray, radius: float
) -> tuple[FloatArray, FloatArray]:
    oc = o - center
    t1, t2 = _quadratic_roots(dd, _rows_dot(d, oc), _rows_dot(oc, oc) - radius * radius)
    t = np.minimum(_positive(t1), _positive(t2))
    hit = np.isfinite(t)
    normals = np.zeros_like(d)
    normals[hit] = (_rows(oc, hit) + t[hit, None] * d[hit]) / radius
    return t, normals


def ray_sphere(
    origins: NDArray, directions: NDArray, center: NDArray, radius: float
) -> tuple[FloatArray, FloatArray]:
    """Rays against a sphere (``center`` m, ``radius`` m)."""
    o, d = _prepare(origins, directions)
    return _sphere(o, d, _rows_dot(d, d), np.asarray(center, dtype=np.float64), radius)


def ray_ellipsoid(
    origins: NDArray, directions: NDArray, center: NDArray, semi_axes: NDArray, rotation: NDArray
) -> tuple[FloatArray, FloatArray]:
    """Rays against an ellipsoid; ``rotation`` maps its own frame to the world."""
    o, d = _prepare(origins, directions)
    rot = np.asarray(rotation, dtype=np.float64)
    e = np.asarray(semi_axes, dtype=np.float64)
    # In coordinates scaled by the semi-axes the ellipsoid is the unit sphere; t is unchanged.
    o_s = ((o - np.asarray(center, dtype=np.float64)) @ rot) / e
    d_s = (d @ rot) / e
    t1, t2 = _quadratic_roots(_rows_dot(d_s, d_s), _rows_dot(d_s, o_s), _rows_dot(o_s, o_s) - 1.0)
    t = np.minimum(_positive(t1), _positive(t2))
    hit = np.isfinite(t)
    normals = np.zeros_like(d)
    local = _rows(o_s, hit) + t[hit, None] * d_s[hit]  # on the unit sphere
    normals[hit] = _unit_rows((local / e) @ rot.T)
    return t, normals


def _side_roots(
    oc: FloatArray, d: FloatArray, axis: FloatArray, length: float, radius: float
) -> tuple[FloatArray, FloatArray]:
    """Hits on the side of the cylinder ``0 <= h <= length`` along ``axis`` from ``oc``'s origin."""
    oc_h, d_h = _rows_dot(oc, axis), d @ axis
    oc_p = oc - (oc_h * axis if oc.ndim == 1 else oc_h[:, None] * axis)
    d_p = d - d_h[:, None] * axis
    t1, t2 = _quadratic_roots(
        _rows_dot(d_p, d_p), _rows_dot(d_p, oc_p), _rows_dot(oc_p, oc_p) - radius * radius
    )
    best = np.full(len(d), np.inf)
    normals = np.zeros_like(d)
    for root in (t1, t2):
        root = _positive(root)
        h = oc_h + root * d_h
        ok = np.isfinite(root) & (h >= 0.0) & (h <= length)
        n = np.zeros_like(d)
        n[ok] = (_rows(oc_p, ok) + root[ok, None] * d_p[ok]) / radius
        _take_min(best, normals, np.where(ok, root, np.inf), n)
    return best, normals


def _axis(a: NDArray, b: NDArray) -> tuple[FloatArray, FloatArray, float]:
    a = np.asarray(a, dtype=np.float64)
    ab = np.asarray(b, dtype=np.float64) - a
    length = float(np.linalg.norm(ab))
    axis = ab / length if length > 0 else np.array([0.0, 0.0, 1.0])
    return a, axis, length


def ray_capsule(
    origins: NDArray, directions: NDArray, a: NDArray, b: NDArray, radius: float
) -> tuple[FloatArray, FloatArray]:
    """Rays against the capsule: segment ``a``-``b`` swept by a ball of ``radius`` (m)."""
    o, d = _prepare(origins, directions)
    a, axis, length = _axis(a, b)
    dd = _rows_dot(d, d)
    t, normals = _sphere(o, d, dd, a, radius)
    _take_min(t, normals, *_sphere(o, d, dd, a + axis * length, radius))
    if length > 0:
        _take_min(t, normals, *_side_roots(o - a, d, axis, length, radius))
    return t, normals


def ray_cylinder(
    origins: NDArray, directions: NDArray, a: NDArray, b: NDArray, radius: float
) -> tuple[FloatArray, FloatArray]:
    """Rays against the finite solid cylinder with flat caps at ``a`` and ``b``."""
    o, d = _prepare(origins, directions)
    a, axis, length = _axis(a, b)
    oc = o - a
    t, normals = _side_roots(oc, d, axis, length, radius)
    oc_h, d_h = _rows_dot(oc, axis), d @ axis
    for cap_h, sign in ((0.0, -1.0), (length, 1.0)):
        with np.errstate(divide="ignore", invalid="ignore"):
            root = _positive((cap_h - oc_h) / d_h)
        p = oc + np.where(np.isfinite(root), root, 0.0)[:, None] * d - cap_h * axis
        ok = np.isfinite(root) & (_rows_dot(p, p) <= radius * radius)
        n = np.broadcast_to(sign * axis, d.shape)
        _take_min(t, normals, np.where(ok, root, np.inf), n)
    return t, normals


def ray_box(
    origins: NDArray, directions: NDArray, center: NDArray, half_extents: NDArray, rotation: NDArray
) -> tuple[FloatArray, FloatArray]:
    """Rays against an oriented box (slab method in the box's own frame)."""
    o, d = _prepare(origins, directions)
    rot = np.asarray(rotation, dtype=np.float64)
    half = np.asarray(half_extents, dtype=np.float64)
    o_l = (o - np.asarray(center, dtype=np.float64)) @ rot
    d_l = d @ rot
    # A zero component would give 0/0 for an origin on a slab boundary; a tiny one gives +-inf.
    d_l = np.where(np.abs(d_l) < 1e-300, 1e-300, d_l)
    t_a = (-half - o_l) / d_l
    t_b = (half - o_l) / d_l
    t_near = np.minimum(t_a, t_b)
    t_far = np.maximum(t_a, t_b)
    enter_axis = np.argmax(t_near, axis=1)
    t_enter = t_near.max(axis=1)
    t_exit = t_far.min(axis=1)
    hit = (t_exit >= t_enter) & (t_exit > _T_MIN)
    from_inside = t_enter <= _T_MIN
    t = np.where(hit, np.where(from_inside, t_exit, t_enter), np.inf)
    axis = np.where(from_inside, np.argmin(t_far, axis=1), enter_axis)
    rows = np.arange(len(d))
    n_local = np.zeros_like(d)
    # Entering through a face means moving against its outward normal; exiting, along it.
    sign = np.where(from_inside, np.sign(d_l[rows, axis]), -np.sign(d_l[rows, axis]))
    n_local[rows, axis] = sign
    normals = np.where(hit[:, None], n_local @ rot.T, 0.0)
    return t, normals
