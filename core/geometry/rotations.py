"""Rotations between directions and the orientation of surface normals.

``rotation_between`` is the Rodrigues rotation that the plane and circle fits use to move a point
set into its own plane; ``orient_normal`` is Alg. 2's sign rule (face the camera) with the guard
for normals seen edge-on.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..validation import as_unit_vector3, as_vector3

FloatArray = NDArray[np.float64]

# Below this |n . z| the camera cannot tell the two sides of a surface apart (edge-on view).
EDGE_ON_COS = 1e-3


def rotation_between(a: ArrayLike, b: ArrayLike) -> FloatArray:
    """The proper rotation ``R`` (3, 3) with the smallest angle such that ``R @ â = b̂``.

    Parameters
    ----------
    a, b
        Non-zero 3-vectors (any length; only their directions count).

    Returns
    -------
    numpy.ndarray
        Orthonormal (3, 3) matrix with determinant +1.

    Notes
    -----
    Rodrigues' formula ``R = I + [k]x + [k]x^2 (1 - cos) / sin^2`` with ``k = â x b̂``. The
    factor ``1 / (1 + cos)`` amplifies rounding as ``b`` turns away from ``a`` (orthonormality off
    by 2e-12 at 179.5 deg, found by a property test), so beyond 120 deg a half-turn about an axis
    orthogonal to ``a`` is composed with the short rotation from ``-a`` to ``b``: orthonormal to
    rounding, though then not the smallest-angle rotation (not unique at 180 deg anyway).

    Examples
    --------
    >>> import numpy as np
    >>> R = rotation_between([1, 0, 0], [0, 1, 0])
    >>> np.allclose(R @ [1, 0, 0], [0, 1, 0])
    True
    """
    ua = as_unit_vector3(a, "a")
    ub = as_unit_vector3(b, "b")
    return _rotation_units(ua, ub)


def _rotation_units(ua: FloatArray, ub: FloatArray) -> FloatArray:
    cos = float(np.clip(ua @ ub, -1.0, 1.0))
    if cos < -0.5:
        # Far from a: 1 / (1 + cos) amplifies rounding in the cross product. Go through a
        # half-turn about an axis orthogonal to a (exact: a -> -a), then the short way to b.
        helper = np.eye(3)[int(np.argmin(np.abs(ua)))]
        axis = np.cross(ua, helper)
        axis /= np.linalg.norm(axis)
        half_turn = 2.0 * np.outer(axis, axis) - np.eye(3)
        return _rotation_units(-ua, ub) @ half_turn
    k = np.cross(ua, ub)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    # (1 - cos) / sin^2 = 1 / (1 + cos): finite here, and exact (identity) for parallel vectors.
    return np.eye(3) + kx + (kx @ kx) * (1.0 / (1.0 + cos))


def orthonormal_frame(normal: ArrayLike) -> FloatArray:
    """A right-handed (3, 3) frame whose third column is the unit ``normal``.

    The first two columns span the plane orthogonal to ``normal``; which pair is chosen depends
    continuously on ``normal`` away from ``-z``.
    """
    n = as_unit_vector3(normal, "normal")
    return rotation_between([0.0, 0.0, 1.0], n)


def orient_normal(
    normal: ArrayLike,
    camera_axis: ArrayLike,
    point: ArrayLike | None = None,
    hip: ArrayLike | None = None,
) -> FloatArray:
    """Turn ``normal`` to face the camera: ``n <- -sign(n . z) n`` (Alg. 2, eq. 2).

    Parameters
    ----------
    normal
        Unit (or any non-zero) surface normal, either sign.
    camera_axis
        The camera's viewing direction ``z`` (from the camera into the scene).
    point, hip
        Surface point and HIP (m). Used only when the surface is seen edge-on (``|n . z|`` below
        ``EDGE_ON_COS``), where ``sign`` would return 0 or a noise-driven sign: the normal is
        then turned towards the HIP, ``n . (hip - point) > 0``.

    Returns
    -------
    numpy.ndarray
        The unit normal with the chosen sign.
    """
    n = as_unit_vector3(normal, "normal")
    z = as_unit_vector3(camera_axis, "camera_axis")
    nz = float(n @ z)
    if abs(nz) >= EDGE_ON_COS or point is None or hip is None:
        return -n if nz > 0.0 else n
    towards = as_vector3(hip, "hip") - as_vector3(point, "point")
    side = float(n @ towards)
    if side != 0.0:
        return n if side > 0.0 else -n
    return -n if nz > 0.0 else n


def frame_from_unit_normal(n: FloatArray) -> FloatArray:
    """A right-handed (3, 3) frame whose third column is the unit vector ``n`` (no validation).

    Duff et al. (2017), "Building an orthonormal basis, revisited": branch-free apart from the
    sign of ``n_z``, exact to rounding, and cheap enough for inner loops (``n`` must be unit).
    """
    nx, ny, nz = float(n[0]), float(n[1]), float(n[2])
    sign = math.copysign(1.0, nz)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    return np.array(
        [
            [1.0 + sign * nx * nx * a, b, nx],
            [sign * b, sign + ny * ny * a, ny],
            [-sign * nx, -ny, nz],
        ]
    )
