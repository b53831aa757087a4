"""Triangle meshes of the simulator's solids, as fine as a chord tolerance asks.

All curved solids are surfaces of revolution (or, for the ellipsoid, a linear image of one), built
from a profile ``(r, h)`` swept around an axis. Every vertex lies on the analytic surface, so the
mesh is inscribed and a ray-cast depth errs on the far side by at most the chord deviation
``tolerance_m`` (measured along the surface normal; along a ray it is ``tolerance_m / cos``
of the incidence angle).

Spacing rules (``R`` a radius of curvature, ``d`` the angular step):

* a triangle of a lat-long grid on a sphere deviates from it by at most ``R d^2 / 4``
  (half the hypotenuse of a cell is its circumradius), so ``d = sqrt(4 tol / R)``;
* an ellipsoid is the linear image of the unit sphere, a triangle's radial gap scales by at most
  the largest semi-axis: ``d = sqrt(4 tol / a_max)``;
* a cylinder's side is flat along the axis; around it the sagitta is ``R d^2 / 8``.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

_MAX_SEGMENTS = 4096  # keeps a silly tolerance from asking for a billion triangles


def _segments(angle_rad: float, step_rad: float, minimum: int) -> int:
    return int(min(max(math.ceil(angle_rad / step_rad), minimum), _MAX_SEGMENTS))


def frame_from_axis(axis: NDArray) -> FloatArray:
    """A right-handed rotation whose third column is the unit ``axis``."""
    u = np.asarray(axis, dtype=np.float64)
    u = u / np.linalg.norm(u)
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(helper, u)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    return np.column_stack((e1, e2, u))


def revolve(radii: NDArray, heights: NDArray, n_around: int) -> tuple[FloatArray, IndexArray]:
    """Sweep the profile ``(radii[i], heights[i])`` (ordered by height) around the local z axis.

    A zero radius at either end becomes a single pole vertex. Triangles wind counter-clockwise
    seen from outside (outward normals for a convex profile).
    """
    radii = np.asarray(radii, dtype=np.float64)
    heights = np.asarray(heights, dtype=np.float64)
    phi = np.arange(n_around) * (2.0 * math.pi / n_around)
    cos_p, sin_p = np.cos(phi), np.sin(phi)
    vertices: list[FloatArray] = []
    rings: list[IndexArray | int] = []
    count = 0
    for r, h in zip(radii, heights, strict=True):
        if r == 0.0:
            vertices.append(np.array([[0.0, 0.0, h]]))
            rings.append(count)
            count += 1
        else:
            vertices.append(np.column_stack((r * cos_p, r * sin_p, np.full(n_around, h))))
            rings.append(np.arange(count, count + n_around))
            count += n_around
    j = np.arange(n_around)
    jn = (j + 1) % n_around
    faces: list[IndexArray] = []
    for lower, upper in itertools.pairwise(rings):
        if isinstance(lower, int) and isinstance(upper, int):
            continue
        if isinstance(lower, int):
            faces.append(np.column_stack((np.full(n_around, lower), upper[jn], upper[j])))
        elif isinstance(upper, int):
            faces.append(np.column_stack((lower[j], lower[jn], np.full(n_around, upper))))
        else:
            faces.append(np.column_stack((lower[j], lower[jn], upper[jn])))
            faces.append(np.column_stack((lower[j], upper[jn], upper[j])))
    return np.vstack(vertices), np.vstack(faces).astype(np.int64)


def _place(vertices: FloatArray, rotation: FloatArray, origin: NDArray) -> FloatArray:
    rot = np.asarray(rotation, dtype=np.float64)
    return vertices @ rot.T + np.asarray(origin, dtype=np.float64)


def _unit_sphere(step_rad: float) -> tuple[FloatArray, IndexArray]:
    n_lat = _segments(math.pi, step_rad, 8)
    theta = np.linspace(-0.5 * math.pi, 0.5 * math.pi, n_lat + 1)
    radii = np.cos(theta)
    radii[[0, -1]] = 0.0
    return revolve(radii, np.sin(theta), _segments(2.0 * math.pi, step_rad, 16))


def sphere_mesh(
    center: NDArray, radius: float, tolerance_m: float
) -> tuple[FloatArray, IndexArray]:
    """Inscribed sphere mesh (vertices ``(V, 3)`` m, triangles ``(F, 3)``)."""
    v, f = _unit_sphere(math.sqrt(4.0 * tolerance_m / radius))
    return v * radius + np.asarray(center, dtype=np.float64), f


def ellipsoid_mesh(
    center: NDArray, semi_axes: NDArray, rotation: NDArray, tolerance_m: float
) -> tuple[FloatArray, IndexArray]:
    """Inscribed ellipsoid mesh; ``rotation`` maps its own frame to the world."""
    e = np.asarray(semi_axes, dtype=np.float64)
    v, f = _unit_sphere(math.sqrt(4.0 * tolerance_m / float(e.max())))
    return _place(v * e, rotation, center), f


def capsule_mesh(
    a: NDArray, b: NDArray, radius: float, tolerance_m: float
) -> tuple[FloatArray, IndexArray]:
    """Inscribed capsule mesh (segment ``a``-``b``, ``radius`` m)."""
    a = np.asarray(a, dtype=np.float64)
    ab = np.asarray(b, dtype=np.float64) - a
    length = float(np.linalg.norm(ab))
    step = math.sqrt(4.0 * tolerance_m / radius)
    n_quarter = _segments(0.5 * math.pi, step, 4)
    alpha = np.linspace(-0.5 * math.pi, 0.0, n_quarter + 1)
    radii = np.concatenate((np.cos(alpha), np.cos(alpha[::-1]))) * radius
    heights = np.concatenate((np.sin(alpha), length / radius - np.sin(alpha[::-1]))) * radius
    radii[[0, -1]] = 0.0
    if length == 0.0:  # a ball: drop the duplicated equator
        radii, heights = np.delete(radii, n_quarter), np.delete(heights, n_quarter)
    v, f = revolve(radii, heights, _segments(2.0 * math.pi, step, 16))
    axis = ab if length > 0 else np.array([0.0, 0.0, 1.0])
    return _place(v, frame_from_axis(axis), a), f


def cylinder_mesh(
    a: NDArray, b: NDArray, radius: float, tolerance_m: float
) -> tuple[FloatArray, IndexArray]:
    """Inscribed finite cylinder with flat caps at ``a`` and ``b``."""
    a = np.asarray(a, dtype=np.float64)
    ab = np.asarray(b, dtype=np.float64) - a
    length = float(np.linalg.norm(ab))
    n_around = _segments(2.0 * math.pi, math.sqrt(8.0 * tolerance_m / radius), 16)
    v, f = revolve([0.0, radius, radius, 0.0], [0.0, 0.0, length, length], n_around)
    return _place(v, frame_from_axis(ab), a), f


def box_mesh(
    center: NDArray, half_extents: NDArray, rotation: NDArray
) -> tuple[FloatArray, IndexArray]:
    """Exact oriented box: 8 vertices, 12 outward-wound triangles."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    v = _place(corners * np.asarray(half_extents, dtype=np.float64), rotation, center)
    # Corner index = 4 * (x > 0) + 2 * (y > 0) + (z > 0).
    f = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],  # -x
            [4, 6, 7],
            [4, 7, 5],  # +x
            [0, 4, 5],
            [0, 5, 1],  # -y
            [2, 3, 7],
            [2, 7, 6],  # +y
            [0, 2, 6],
            [0, 6, 4],  # -z
            [1, 5, 7],
            [1, 7, 3],  # +z
        ],
        dtype=np.int64,
    )
    return v, f
