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
    """Row-wise dot products; a single (3,) operand (the common ray origin) is not broadcast.

    Written out component by component rather than ``@``/``einsum``: BLAS and einsum may round a
    row differently depending on how many rows there are and where it sits (measured: a single
    row of ``d @ v`` differs in the last bit from the same row inside a longer array). A ray's
    hit must not depend on which other rays are cast with it (a region-of-interest render is
    bit for bit the full render there), and plain element-wise products and sums guarantee it.
    """
    if a.ndim == 1 and b.ndim == 1:
        return float(a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
    a0, a1, a2 = (a[..., i] for i in range(3))
    b0, b1, b2 = (b[..., i] for i in range(3))
    return a0 * b0 + a1 * b1 + a2 * b2


def _rows_matmul(a: FloatArray, m: FloatArray) -> FloatArray:
    """``a @ m`` for ``(N, 3)`` or ``(3,)`` rows and a 3x3 ``m``, row by row (see ``_rows_dot``)."""
    a = np.asarray(a, dtype=np.float64)
    m = np.asarray(m, dtype=np.float64)
    return a[..., 0:1] * m[0] + a[..., 1:2] * m[1] + a[..., 2:3] * m[2]


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
    norm = np.sqrt(_rows_dot(v, v))[:, None]
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
    o_s = _rows_matmul(o - np.asarray(center, dtype=np.float64), rot) / e
    d_s = _rows_matmul(d, rot) / e
    t1, t2 = _quadratic_roots(_rows_dot(d_s, d_s), _rows_dot(d_s, o_s), _rows_dot(o_s, o_s) - 1.0)
    t = np.minimum(_positive(t1), _positive(t2))
    hit = np.isfinite(t)
    normals = np.zeros_like(d)
    local = _rows(o_s, hit) + t[hit, None] * d_s[hit]  # on the unit sphere
    normals[hit] = _unit_rows(_rows_matmul(local / e, rot.T))
    return t, normals


def _side_roots(
    oc: FloatArray, d: FloatArray, axis: FloatArray, length: float, radius: float
) -> tuple[FloatArray, FloatArray]:
    """Hits on the side of the cylinder ``0 <= h <= length`` along ``axis`` from ``oc``'s origin."""
    oc_h, d_h = _rows_dot(oc, axis), _rows_dot(d, axis)
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


def capsule_depths(
    dirs: tuple[FloatArray, FloatArray, FloatArray],
    dd: FloatArray,
    origin: FloatArray,
    a: FloatArray,
    b: FloatArray,
    radius: float,
) -> FloatArray:
    """``t`` of rays from ``origin`` (outside the capsule) against the capsule ``a``-``b``.

    The lean form of :func:`ray_capsule` for many capsules (the robot's links) over the same
    rays: depth only (normals of the winners later, :func:`capsule_normals`), the rays given as
    the three coordinate planes ``dirs`` (any shape, float64) and their squared lengths ``dd``,
    everything that depends on the capsule alone computed once in Python floats. The smallest
    positive root of the side (infinite cylinder, kept where it lies between the ends) and of
    the two end balls, each in cancellation-free form; ``inf`` on a miss. Element-wise only, so
    a ray's ``t`` does not depend on the other rays (see :func:`_rows_dot`).
    """
    d0, d1, d2 = dirs
    oa = [float(origin[i]) - float(a[i]) for i in range(3)]
    ba = [float(b[i]) - float(a[i]) for i in range(3)]
    r2 = float(radius) * float(radius)
    baba = ba[0] * ba[0] + ba[1] * ba[1] + ba[2] * ba[2]
    baoa = ba[0] * oa[0] + ba[1] * oa[1] + ba[2] * oa[2]
    oaoa = oa[0] * oa[0] + oa[1] * oa[1] + oa[2] * oa[2]
    ob = [oa[i] - ba[i] for i in range(3)]
    obob = ob[0] * ob[0] + ob[1] * ob[1] + ob[2] * ob[2]
    # Side: with w = oa + t d, |w|^2 baba - (w . ba)^2 = r^2 baba, i.e. A t^2 + 2 B t + C = 0.
    c_side = baba * oaoa - baoa * baoa - r2 * baba
    bard = d0 * ba[0] + d1 * ba[1] + d2 * ba[2]
    rdoa = d0 * oa[0] + d1 * oa[1] + d2 * oa[2]
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.full(np.shape(dd), np.inf)
        if c_side > 0.0:  # the origin is outside the infinite cylinder: the side can be entered
            half_b = baba * rdoa - baoa * bard
            disc = half_b * half_b - (baba * dd - bard * bard) * c_side
            t_side = c_side / (np.sqrt(disc) - half_b)
            y = baoa + t_side * bard
            ok = (half_b < 0.0) & (disc >= 0.0) & (y > 0.0) & (y < baba)
            np.copyto(t, t_side, where=ok)
        for half_b, c in ((rdoa, oaoa - r2), (rdoa - bard, obob - r2)):
            # An end ball in front of the origin (c > 0: the origin is outside it).
            disc = half_b * half_b - dd * c
            t_ball = c / (np.sqrt(disc) - half_b)
            ok = (half_b < 0.0) & (disc >= 0.0) & (t_ball < t)
            np.copyto(t, t_ball, where=ok)
    return t


def capsule_normals(
    points: FloatArray, a: FloatArray, b: FloatArray, radius: FloatArray
) -> FloatArray:
    """Outward unit normals at ``points`` (M, 3) on capsules with rows ``a``, ``b``, ``radius``."""
    ba = b - a
    pa = points - a
    baba = _rows_dot(ba, ba)
    with np.errstate(invalid="ignore", divide="ignore"):
        h = np.clip(np.where(baba > 0.0, _rows_dot(pa, ba) / baba, 0.0), 0.0, 1.0)
    return _unit_rows(pa - h[:, None] * ba)


def ray_cylinder(
    origins: NDArray, directions: NDArray, a: NDArray, b: NDArray, radius: float
) -> tuple[FloatArray, FloatArray]:
    """Rays against the finite solid cylinder with flat caps at ``a`` and ``b``."""
    o, d = _prepare(origins, directions)
    a, axis, length = _axis(a, b)
    oc = o - a
    t, normals = _side_roots(oc, d, axis, length, radius)
    oc_h, d_h = _rows_dot(oc, axis), _rows_dot(d, axis)
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
    o_l = _rows_matmul(o - np.asarray(center, dtype=np.float64), rot)
    d_l = _rows_matmul(d, rot)
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
    normals = np.where(hit[:, None], _rows_matmul(n_local, rot.T), 0.0)
    return t, normals
