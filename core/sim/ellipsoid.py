"""Closest point on an axis-aligned ellipsoid: Eberly's robust bisection on the Lagrange parameter.

Reference: D. Eberly, "Distance from a Point to an Ellipse, an Ellipsoid, or a Hyperellipsoid"
(Geometric Tools, 2013). The point is reflected into the first octant and the semi-axes sorted
(``e0 >= e1 >= e2``); the closest point ``x`` satisfies ``x_i = r_i y_i / (s + r_i)`` with
``r_i = (e_i / e2)^2`` for the root ``s`` of a monotone function, found by bisection until the
bracket stops shrinking (full double precision, no tolerance to tune). We bisect on ``u = s + 1``
with ``r_i - 1`` formed as ``(e_i - e2)(e_i + e2) / e2^2``: that keeps queries within 1e-16 of the
centre of a body with two equal semi-axes from dividing by zero. Points on a symmetry plane
are reduced to the ellipse problem; that is where the closest point may leave the plane (a point
inside, near the centre), and those cases have closed forms.

Near the centre the root ``u`` is of the order of the query's components along the smallest axis
(or axes, when several are equal); a query a subnormal step from the centre would put ``u`` among
the subnormals, where a double keeps only a few bits, and the point ``y / u`` off the surface
(1e-11 was seen). When ``u`` is that small it is negligible next to every ``r_i - 1 > 0``, the
equation decouples and has a closed form (:func:`_negligible_root`), evaluated with the small
components scaled by a power of two first (exact): full precision there too.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# Bisection halves a bracket of doubles; ~1100 halvings reach any double from any other.
_MAX_BISECTIONS = 1200


def _bisect(ratios_sq, lo: float, hi: float) -> float:
    """Root ``u`` in ``[lo, hi]`` of the decreasing ``ratios_sq(u) - 1`` by bisection.

    Stops when the midpoint equals an end of the bracket: full double precision, no tolerance.
    """
    u = 0.5 * (lo + hi)
    for _ in range(_MAX_BISECTIONS):
        u = 0.5 * (lo + hi)
        if u in (lo, hi):
            break
        g = ratios_sq(u) - 1.0
        if g > 0:
            lo = u
        elif g < 0:
            hi = u
        else:
            break
    return u


def _root_2d(r0m1: float, n0: float, z1: float, g: float) -> float:
    # Eberly's s shifted by one, u = s + 1: his bracket end z1 - 1 rounds to -1 for a query near
    # the centre, and s + 1 then divides by zero; u's bracket [z1, ...] stays positive.
    hi = 1.0 if g < 0 else math.hypot(n0, z1)
    return _bisect(lambda u: (n0 / (u + r0m1)) ** 2 + (z1 / u) ** 2, z1, hi)


def _root_3d(r0m1: float, r1m1: float, n0: float, n1: float, z2: float, g: float) -> float:
    hi = 1.0 if g < 0 else math.sqrt(n0 * n0 + n1 * n1 + z2 * z2)
    return _bisect(
        lambda u: (n0 / (u + r0m1)) ** 2 + (n1 / (u + r1m1)) ** 2 + (z2 / u) ** 2, z2, hi
    )


def _negligible_root(e: tuple[float, ...], y: tuple[float, ...]) -> list[float] | None:
    """The closest point when the root ``u`` is negligible next to every ``r_i - 1 > 0``.

    ``e`` sorted decreasing (the smallest last), ``y > 0`` componentwise. The axes equal to the
    smallest (``r_i = 1``) give ``x_i = y_i / u``; the others ``x_i = r_i y_i / (u + r_i - 1)``.
    If ``u`` is below half an ulp of every ``r_i - 1 > 0`` (and of 1) those are exactly
    ``x_i = e_i^2 y_i / (e_i^2 - e_min^2)`` in floating point, and the constraint leaves
    ``|x_equal| = e_min sqrt(1 - sum_others (x_i / e_i)^2)`` along ``y_equal``: the root in
    closed form. Returns ``None`` where ``u`` is not that small (or the query is outside those
    planes' ellipse), for the bisection. With all axes equal (a sphere) this is always exact.
    """
    e_min = e[-1]
    discr = 1.0
    gap = math.inf  # smallest r_i - 1 > 0
    x = [0.0] * len(e)
    equal: list[int] = []
    for i, (ei, yi) in enumerate(zip(e, y, strict=True)):
        if ei == e_min:
            equal.append(i)
            continue
        d = (ei - e_min) * (ei + e_min)
        xde = ei * yi / d
        discr -= xde * xde
        x[i] = ei * xde
        gap = min(gap, d / (e_min * e_min))
    if not discr > 0.0:
        return None
    # The equal-axis components scaled by a power of two (exact, subnormals included) so that
    # their norm and direction keep every bit.
    shift = -math.frexp(max(y[i] for i in equal))[1]
    scaled = [math.ldexp(y[i], shift) for i in equal]
    norm = math.hypot(*scaled)
    root = math.sqrt(discr)
    u = math.ldexp(norm, -shift) / e_min / root  # may underflow: only compared
    # Exact when u + (r_i - 1) rounds to r_i - 1; and then q - x leaves the normal by u |x_equal|
    # at most (below 2^-54 e_min): u must be under 2^-54 of both. A sphere: always exact.
    if gap != math.inf and not u < math.ldexp(min(gap, 1.0), -54):
        return None
    for i, ys in zip(equal, scaled, strict=True):
        x[i] = e_min * root * (ys / norm)
    return x


def _ellipse(e0: float, e1: float, y0: float, y1: float) -> tuple[float, float]:
    """Closest point for ``e0 >= e1 > 0`` and ``y0, y1 >= 0``."""
    if y1 > 0:
        if y0 > 0:
            z0, z1 = y0 / e0, y1 / e1
            g = z0 * z0 + z1 * z1 - 1.0
            if g == 0:
                return y0, y1
            closed = _negligible_root((e0, e1), (y0, y1))
            if closed is not None:
                return closed[0], closed[1]
            r0 = (e0 / e1) ** 2
            r0m1 = (e0 - e1) * (e0 + e1) / (e1 * e1)  # r0 - 1 without cancellation
            u = _root_2d(r0m1, r0 * z0, z1, g)
            return r0 * y0 / (u + r0m1), y1 / u
        return 0.0, e1
    numer0, denom0 = e0 * y0, e0 * e0 - e1 * e1
    if numer0 < denom0:
        # Inside, on the major axis, near the centre: the nearest point is off the axis.
        xde0 = numer0 / denom0
        return e0 * xde0, e1 * math.sqrt(max(1.0 - xde0 * xde0, 0.0))
    return e0, 0.0


def _ellipsoid_sorted(e: FloatArray, y: FloatArray) -> FloatArray:
    """Closest point for sorted ``e0 >= e1 >= e2 > 0`` and ``y >= 0`` (first octant)."""
    e0, e1, e2 = (float(v) for v in e)
    y0, y1, y2 = (float(v) for v in y)
    if y2 > 0:
        if y1 > 0:
            if y0 > 0:
                z0, z1, z2 = y0 / e0, y1 / e1, y2 / e2
                g = z0 * z0 + z1 * z1 + z2 * z2 - 1.0
                if g == 0:
                    return np.array([y0, y1, y2])
                closed = _negligible_root((e0, e1, e2), (y0, y1, y2))
                if closed is not None:
                    return np.array(closed)
                r0, r1 = (e0 / e2) ** 2, (e1 / e2) ** 2
                r0m1 = (e0 - e2) * (e0 + e2) / (e2 * e2)
                r1m1 = (e1 - e2) * (e1 + e2) / (e2 * e2)
                u = _root_3d(r0m1, r1m1, r0 * z0, r1 * z1, z2, g)
                return np.array([r0 * y0 / (u + r0m1), r1 * y1 / (u + r1m1), y2 / u])
            x1, x2 = _ellipse(e1, e2, y1, y2)
            return np.array([0.0, x1, x2])
        if y0 > 0:
            x0, x2 = _ellipse(e0, e2, y0, y2)
            return np.array([x0, 0.0, x2])
        return np.array([0.0, 0.0, e2])
    denom0, denom1 = e0 * e0 - e2 * e2, e1 * e1 - e2 * e2
    numer0, numer1 = e0 * y0, e1 * y1
    if numer0 < denom0 and numer1 < denom1:
        # Inside, near the centre of the smallest axis: the nearest point leaves the y2 = 0 plane.
        xde0, xde1 = numer0 / denom0, numer1 / denom1
        discr = 1.0 - xde0 * xde0 - xde1 * xde1
        if discr > 0:
            return np.array([e0 * xde0, e1 * xde1, e2 * math.sqrt(discr)])
    x0, x1 = _ellipse(e0, e1, y0, y1)
    return np.array([x0, x1, 0.0])


def closest_point_on_ellipsoid(semi_axes: FloatArray, point: FloatArray) -> FloatArray:
    """Closest surface point of the ellipsoid ``sum (x_i / a_i)^2 = 1`` to ``point``.

    Parameters
    ----------
    semi_axes
        ``(3,)`` positive semi-axes in m (any order; equal axes are fine).
    point
        ``(3,)`` query in the ellipsoid's own frame (centred, axis-aligned), m; inside or outside.

    Returns
    -------
    numpy.ndarray
        ``(3,)`` closest point on the surface in the same frame, m. Where several points are
        equally close (a query on a symmetry axis), one of them is returned.
    """
    e = np.asarray(semi_axes, dtype=np.float64)
    q = np.asarray(point, dtype=np.float64)
    order = np.argsort(-e, kind="stable")
    signs = np.where(q[order] < 0, -1.0, 1.0)
    x_sorted = _ellipsoid_sorted(e[order], np.abs(q[order])) * signs
    out = np.empty(3)
    out[order] = x_sorted
    return out


def ellipsoid_normal(semi_axes: FloatArray, surface_point: FloatArray) -> FloatArray:
    """Outward unit normal at a surface point (gradient of ``sum (x_i / a_i)^2``), own frame."""
    e = np.asarray(semi_axes, dtype=np.float64)
    grad = np.asarray(surface_point, dtype=np.float64) / (e * e)
    return grad / np.linalg.norm(grad)  # never zero on the surface: some |x_i| >= min(a) / sqrt(3)
