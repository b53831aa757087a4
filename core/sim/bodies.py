"""Analytic solids the simulated patient (and the room) are made of.

Each body has a ``name``, an ISO/TS 15066 body ``part`` and a rigid translation over time,
``offset_m + velocity_mps * t``; the shape parameters give the pose at ``t = 0`` without offset
(its *rest* pose). Each answers three questions exactly in the world frame:

* :meth:`Body.closest_point` -- the surface point nearest to a query (the HIP), the outward unit
  normal there and the signed distance (negative inside);
* :meth:`Body.intersect_rays` -- closed-form ray hits (used to check the meshes, and for tests);
* :meth:`Body.mesh_arrays` -- an inscribed triangle mesh for Open3D ray casting.

Example
-------
>>> head = SphereBody(name="head", part="skull_forehead", center=[0, 0, 1.25], radius_m=0.09)
>>> sp = head.closest_point([0.2, 0, 1.25])
>>> round(sp.distance_m, 6), sp.normal.tolist()
(0.11, [1.0, 0.0, 0.0])
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import cached_property
from typing import ClassVar, NamedTuple, Self

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..validation import as_finite_scalar, as_points, as_vector3
from . import meshing, raycast
from .ellipsoid import closest_point_on_ellipsoid, ellipsoid_normal

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

#: ISO/TS 15066 body regions (Annex A), plus ``"background"`` for the room.
BODY_PARTS: tuple[str, ...] = (
    "skull_forehead",
    "face",
    "neck",
    "back_shoulders",
    "chest",
    "belly",
    "pelvis",
    "upper_arm",
    "forearm",
    "hand",
    "thigh",
    "lower_leg",
    "foot",
    "background",
)

#: Default chord tolerance of the meshes (m): ray-cast depth within 0.05 mm up to 78 deg incidence.
MESH_TOLERANCE_M = 1e-5

_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)

#: Round-off of a closest-point computation, relative to the magnitude of the coordinates involved
#: (the query's, the body's and its displacement's): ~64 ulps. A query closer than that to an axis
#: (or a centre) of a body is *on* it: its offset from it is round-off, not a direction.
_ROUND_OFF = 64 * float(np.finfo(np.float64).eps)
_PLUS_Z = np.array([0.0, 0.0, 1.0])
_PLUS_Z.setflags(write=False)


class SurfacePoint(NamedTuple):
    """A closest surface point: ``point`` (3,) m, outward unit ``normal`` (3,), ``distance_m``."""

    point: FloatArray
    normal: FloatArray
    distance_m: float


def _frozen_vec(value: ArrayLike, name: str) -> FloatArray:
    arr = np.array(as_vector3(value, name), dtype=np.float64)
    arr.setflags(write=False)
    return arr


def _positive(value: object, name: str) -> float:
    out = as_finite_scalar(value, name)
    if out <= 0:
        raise InputError(f"{name} = {out}: must be positive")
    return out


def _rotation(value: ArrayLike, name: str = "rotation") -> FloatArray:
    rot = np.array(value, dtype=np.float64)
    if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
        raise InputError(f"{name}: expected a finite (3, 3) matrix, got shape {rot.shape}")
    if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        raise InputError(f"{name}: must be a proper rotation matrix (orthonormal, det +1)")
    # Re-orthonormalise so that a rotation given to 6 digits is exact to the last bit.
    u, _, vt = np.linalg.svd(rot)
    rot = u @ vt
    rot.setflags(write=False)
    return rot


def _any_perpendicular(axis: FloatArray) -> FloatArray:
    out = meshing.frame_from_axis(axis)[:, 0]
    out.setflags(write=False)
    return out


def _magnitude(v: FloatArray) -> float:
    """Largest absolute coordinate of a (3,) vector."""
    x, y, z = v.tolist()
    return max(abs(x), abs(y), abs(z))


_MESH_CACHE: OrderedDict[tuple, tuple[FloatArray, IndexArray]] = OrderedDict()
_MESH_CACHE_SIZE = 64


@dataclass(frozen=True, kw_only=True, eq=False)
class Body:
    """Base of the analytic bodies (use a subclass). Positions in m, velocity in m/s."""

    #: False when the mesh is the exact surface (flat faces only), so hits need no refinement.
    curved: ClassVar[bool] = True

    name: str
    part: str
    velocity_mps: FloatArray = field(default_factory=lambda: _ZERO3)
    offset_m: FloatArray = field(default_factory=lambda: _ZERO3)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"name: expected a non-empty string, got {self.name!r}")
        if self.part not in BODY_PARTS:
            raise InputError(f"part = {self.part!r}: must be one of {', '.join(BODY_PARTS)}")
        object.__setattr__(self, "velocity_mps", _frozen_vec(self.velocity_mps, "velocity_mps"))
        object.__setattr__(self, "offset_m", _frozen_vec(self.offset_m, "offset_m"))

    # ----- motion ------------------------------------------------------------------------------
    def displacement(self, t: float = 0.0) -> FloatArray:
        """Translation of the body from its rest pose at time ``t`` (s), m."""
        return self.offset_m + self.velocity_mps * as_finite_scalar(t, "t")

    def moved(self, offset: ArrayLike) -> Self:
        """A copy translated by ``offset`` (m) more; the shape and its mesh stay shared."""
        return dataclasses.replace(self, offset_m=self.offset_m + as_vector3(offset, "offset"))

    @property
    def is_static(self) -> bool:
        """True when the body never moves from its rest pose."""
        return not (np.any(self.offset_m) or np.any(self.velocity_mps))

    # ----- queries in the world frame ----------------------------------------------------------
    def closest_point(self, hip: ArrayLike, t: float = 0.0) -> SurfacePoint:
        """Closest surface point to ``hip`` (m) at time ``t`` (s), exactly.

        Returns
        -------
        SurfacePoint
            ``(point, normal, distance_m)``: the surface point, the outward unit surface normal
            there, and the signed distance from the surface to ``hip`` (negative inside).
            On an edge of a box or cylinder, ``normal`` is the direction from the point to an
            outside ``hip``. Where several points are equally near (``hip`` on an axis of a
            capsule or cylinder, at a centre) one of them is returned; ``hip`` within round-off
            of such a place counts as on it, so the answer is on the surface wherever ``hip``
            is, also 1e3 m from the origin.
        """
        hip = as_vector3(hip, "hip")
        shift = self.displacement(t)
        noise = _ROUND_OFF * (_magnitude(hip) + _magnitude(shift) + self._size_m)
        point, normal, dist = self._closest_rest(hip - shift, noise)
        return SurfacePoint(point + shift, normal, float(dist))

    def intersect_rays(
        self, origins: ArrayLike, directions: ArrayLike, t: float = 0.0
    ) -> tuple[FloatArray, FloatArray]:
        """Closed-form hits ``(t_hit (M,), normals (M, 3))`` of rays at time ``t`` (s).

        ``t_hit`` is in units of each direction's length (``inf`` on a miss).
        """
        o = np.asarray(origins, dtype=np.float64)
        o = as_vector3(o, "origins") if o.shape == (3,) else as_points(o, "origins")
        return self.intersect_rays_rest(o - self.displacement(t), directions)

    def intersect_rays_rest(
        self, origins: ArrayLike, directions: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """As :meth:`intersect_rays` with the body in its rest pose (no offset, no motion)."""
        return self._intersect_rest(
            np.asarray(origins, dtype=np.float64), as_points(directions, "directions")
        )

    def mesh_arrays(
        self, t: float = 0.0, tolerance_m: float = MESH_TOLERANCE_M
    ) -> tuple[FloatArray, IndexArray]:
        """Inscribed mesh at time ``t``: vertices ``(V, 3)`` m and triangles ``(F, 3)``."""
        v, f = self.rest_mesh_arrays(tolerance_m)
        return v + self.displacement(t), f

    def mesh(
        self, t: float = 0.0, tolerance_m: float = MESH_TOLERANCE_M
    ) -> o3d.geometry.TriangleMesh:
        """The inscribed mesh at time ``t`` as an Open3D legacy mesh (with vertex normals)."""
        v, f = self.mesh_arrays(t, tolerance_m)
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32))
        )
        mesh.compute_vertex_normals()
        return mesh

    def rest_mesh_arrays(
        self, tolerance_m: float = MESH_TOLERANCE_M
    ) -> tuple[FloatArray, IndexArray]:
        """The mesh in the rest pose, cached by shape and tolerance (read-only arrays)."""
        tol = _positive(tolerance_m, "tolerance_m")
        key = (self.shape_key(), tol)
        cached = _MESH_CACHE.get(key)
        if cached is None:
            v, f = self._mesh_rest(tol)
            v.setflags(write=False)
            f.setflags(write=False)
            cached = _MESH_CACHE[key] = (v, f)
            if len(_MESH_CACHE) > _MESH_CACHE_SIZE:
                _MESH_CACHE.popitem(last=False)
        else:
            _MESH_CACHE.move_to_end(key)
        return cached

    def bounds(self, t: float = 0.0) -> tuple[FloatArray, FloatArray]:
        """Axis-aligned bounding box ``(lo, hi)`` at time ``t``, m."""
        lo, hi = self._rest_box
        shift = self.displacement(t)
        return lo + shift, hi + shift

    # ----- per shape ---------------------------------------------------------------------------
    def shape_key(self) -> tuple:
        """Hashable identity of the rest shape (type and exact parameters)."""
        raise NotImplementedError

    def distance_lower_bound(self, hip: FloatArray, t: float = 0.0) -> float:
        """A bound (m) the signed distance of :meth:`closest_point` never falls below: the
        distance from ``hip`` to the body's bounding box at ``t``, ``-inf`` inside the box."""
        lo, hi = self._rest_box
        p = hip - self.displacement(t)
        gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
        if not gap.any():
            return -math.inf
        return float(np.sqrt(gap @ gap))

    @cached_property
    def _rest_box(self) -> tuple[FloatArray, FloatArray]:
        return self._bounds_rest()

    @cached_property
    def _size_m(self) -> float:
        """Magnitude of the rest shape's coordinates (m): scales the round-off tolerance."""
        lo, hi = self._rest_box
        return max(_magnitude(lo), _magnitude(hi))

    def _closest_rest(self, p: FloatArray, noise: float) -> tuple[FloatArray, FloatArray, float]:
        """Closest point to ``p`` in the rest pose; offsets up to ``noise`` (m) are round-off."""
        raise NotImplementedError

    def _intersect_rest(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        raise NotImplementedError

    def _mesh_rest(self, tolerance_m: float) -> tuple[FloatArray, IndexArray]:
        raise NotImplementedError

    def _bounds_rest(self) -> tuple[FloatArray, FloatArray]:
        raise NotImplementedError


def _unit(v: FloatArray) -> FloatArray:
    """``v`` (non-zero) scaled to unit length, also when its components are subnormal: squaring
    1e-160 underflows, and ``v / |v|`` came out 1.2e-5 too long (hypothesis found it)."""
    scaled = v / float(np.max(np.abs(v)))
    return scaled / float(np.linalg.norm(scaled))


def _key(*values: object) -> tuple:
    return tuple(v.tobytes() if isinstance(v, np.ndarray) else v for v in values)


@dataclass(frozen=True, kw_only=True, eq=False)
class SphereBody(Body):
    """Sphere: ``center`` (3,) m, ``radius_m``."""

    center: FloatArray
    radius_m: float

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "center", _frozen_vec(self.center, "center"))
        object.__setattr__(self, "radius_m", _positive(self.radius_m, "radius_m"))

    def shape_key(self) -> tuple:
        return _key("sphere", self.center, self.radius_m)

    def _closest_rest(self, p: FloatArray, noise: float) -> tuple[FloatArray, FloatArray, float]:
        v = p - self.center
        r = float(np.linalg.norm(v))
        # At the centre every direction is nearest; +z is as good as any. Within round-off of it
        # the direction is noise (and a subnormal offset would not even normalise to unit length).
        n = v / r if r > noise else _PLUS_Z
        return self.center + self.radius_m * n, n, r - self.radius_m

    def _intersect_rest(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        return raycast.ray_sphere(o, d, self.center, self.radius_m)

    def _mesh_rest(self, tolerance_m: float) -> tuple[FloatArray, IndexArray]:
        return meshing.sphere_mesh(self.center, self.radius_m, tolerance_m)

    def _bounds_rest(self) -> tuple[FloatArray, FloatArray]:
        return self.center - self.radius_m, self.center + self.radius_m


@dataclass(frozen=True, kw_only=True, eq=False)
class EllipsoidBody(Body):
    """Ellipsoid: ``center``, ``semi_axes_m`` (3,) along ``rotation``'s columns (own->world)."""

    center: FloatArray
    semi_axes_m: FloatArray
    rotation: FloatArray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "center", _frozen_vec(self.center, "center"))
        axes = _frozen_vec(self.semi_axes_m, "semi_axes_m")
        if np.any(axes <= 0):
            raise InputError(f"semi_axes_m = {axes.tolist()}: must be positive")
        object.__setattr__(self, "semi_axes_m", axes)
        object.__setattr__(self, "rotation", _rotation(self.rotation))

    def shape_key(self) -> tuple:
        return _key("ellipsoid", self.center, self.semi_axes_m, self.rotation)

    def _closest_rest(self, p: FloatArray, noise: float) -> tuple[FloatArray, FloatArray, float]:
        q = (p - self.center) @ self.rotation
        x = closest_point_on_ellipsoid(self.semi_axes_m, q)
        n_local = ellipsoid_normal(self.semi_axes_m, x)
        dist = float(np.linalg.norm(q - x))
        if np.sum((q / self.semi_axes_m) ** 2) < 1.0:
            dist = -dist
        return self.center + self.rotation @ x, self.rotation @ n_local, dist

    def _intersect_rest(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        return raycast.ray_ellipsoid(o, d, self.center, self.semi_axes_m, self.rotation)

    def _mesh_rest(self, tolerance_m: float) -> tuple[FloatArray, IndexArray]:
        return meshing.ellipsoid_mesh(self.center, self.semi_axes_m, self.rotation, tolerance_m)

    def _bounds_rest(self) -> tuple[FloatArray, FloatArray]:
        reach = np.sqrt(((self.rotation * self.semi_axes_m) ** 2).sum(axis=1))
        return self.center - reach, self.center + reach


def _axis_frame(a: FloatArray, b: FloatArray) -> tuple[FloatArray, float]:
    ab = b - a
    length = float(np.linalg.norm(ab))
    return (ab / length if length > 0 else np.array([0.0, 0.0, 1.0])), length


@dataclass(frozen=True, kw_only=True, eq=False)
class CapsuleBody(Body):
    """Capsule: segment ``a``-``b`` (m) swept by a ball of ``radius_m``."""

    a: FloatArray
    b: FloatArray
    radius_m: float

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "a", _frozen_vec(self.a, "a"))
        object.__setattr__(self, "b", _frozen_vec(self.b, "b"))
        object.__setattr__(self, "radius_m", _positive(self.radius_m, "radius_m"))

    def shape_key(self) -> tuple:
        return _key("capsule", self.a, self.b, self.radius_m)

    @cached_property
    def _frame(self) -> tuple[FloatArray, float, FloatArray]:
        """Unit axis a -> b, length and a fixed unit perpendicular to the axis."""
        axis, length = _axis_frame(self.a, self.b)
        axis.setflags(write=False)
        return axis, length, _any_perpendicular(axis)

    def _closest_rest(self, p: FloatArray, noise: float) -> tuple[FloatArray, FloatArray, float]:
        axis, length, perpendicular = self._frame
        d = p - self.a
        s = float(d @ axis)
        if s <= 0.0:  # the ball at a (its hemisphere away from b: v . axis = s <= 0)
            on_axis, v = self.a, d
        elif s >= length:
            on_axis, v = self.b, p - self.b
        else:  # the side: the offset from the axis is radial; its axial part is round-off
            on_axis = self.a + s * axis
            v = p - on_axis
            v = v - float(v @ axis) * axis
        r = float(np.linalg.norm(v))
        # Exactly on the axis every radial direction is nearest: take a fixed one. Just off it
        # the offset's own direction, even if it is round-off: a fixed one would put the point
        # up to 2 r from where the distance r - radius says (a query 1 km out, 2e-11 m off).
        n = _unit(v) if r > 0.0 else perpendicular
        return on_axis + self.radius_m * n, n, r - self.radius_m

    def _intersect_rest(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        return raycast.ray_capsule(o, d, self.a, self.b, self.radius_m)

    def _mesh_rest(self, tolerance_m: float) -> tuple[FloatArray, IndexArray]:
        return meshing.capsule_mesh(self.a, self.b, self.radius_m, tolerance_m)

    def _bounds_rest(self) -> tuple[FloatArray, FloatArray]:
        r = self.radius_m
        return np.minimum(self.a, self.b) - r, np.maximum(self.a, self.b) + r


@dataclass(frozen=True, kw_only=True, eq=False)
class CylinderBody(Body):
    """Finite solid cylinder with flat caps at ``a`` and ``b`` (m), ``radius_m``."""

    a: FloatArray
    b: FloatArray
    radius_m: float

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "a", _frozen_vec(self.a, "a"))
        object.__setattr__(self, "b", _frozen_vec(self.b, "b"))
        object.__setattr__(self, "radius_m", _positive(self.radius_m, "radius_m"))
        if not np.linalg.norm(self.b - self.a) > 0:
            raise InputError("b: must differ from a (a cylinder needs a length)")

    def shape_key(self) -> tuple:
        return _key("cylinder", self.a, self.b, self.radius_m)

    @cached_property
    def _frame(self) -> tuple[FloatArray, float, FloatArray, FloatArray]:
        """Unit axis a -> b, half length, a fixed unit perpendicular, the middle of a-b."""
        axis, length = _axis_frame(self.a, self.b)
        mid = 0.5 * (self.a + self.b)
        axis.setflags(write=False)
        mid.setflags(write=False)
        return axis, 0.5 * length, _any_perpendicular(axis), mid

    def _closest_rest(self, p: FloatArray, noise: float) -> tuple[FloatArray, FloatArray, float]:
        axis, half, perpendicular, mid = self._frame
        rel = p - mid
        h = float(rel @ axis)
        w = rel - h * axis
        w = w - float(w @ axis) * axis  # radial: the axial part left is round-off
        rho = float(np.linalg.norm(w))
        # Exactly on the axis every radial direction is nearest: take a fixed one; just off it
        # the offset's own direction (as the capsule: the point agrees with rho - radius).
        radial = _unit(w) if rho > 0.0 else perpendicular
        side = 1.0 if h >= 0 else -1.0
        d_r, d_h = rho - self.radius_m, abs(h) - half
        if d_r <= 0 and d_h <= 0:  # inside: leave through the nearer of side and cap
            if d_r >= d_h:
                return mid + h * axis + self.radius_m * radial, radial, d_r
            return mid + side * half * axis + w, side * axis, d_h
        if d_h <= 0:
            return mid + h * axis + self.radius_m * radial, radial, d_r
        if d_r <= 0:
            return mid + side * half * axis + w, side * axis, d_h
        # Beyond the rim: the nearest point is on the rim circle, and p - rim is
        # d_r radial + d_h side axis exactly; the normal is built from those two (orthonormal)
        # directions rather than from p - rim, whose round-off near the edge is of the order of
        # the distance itself. Scaled by the larger part first: unit even for subnormal parts.
        rim = mid + side * half * axis + self.radius_m * radial
        big = max(d_r, d_h)
        c_r, c_h = d_r / big, d_h / big
        k = math.hypot(c_r, c_h)
        normal = (c_r / k) * radial + (side * c_h / k) * axis
        return rim, normal, math.hypot(d_r, d_h)

    def _intersect_rest(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        return raycast.ray_cylinder(o, d, self.a, self.b, self.radius_m)

    def _mesh_rest(self, tolerance_m: float) -> tuple[FloatArray, IndexArray]:
        return meshing.cylinder_mesh(self.a, self.b, self.radius_m, tolerance_m)

    def _bounds_rest(self) -> tuple[FloatArray, FloatArray]:
        axis, _ = _axis_frame(self.a, self.b)
        reach = self.radius_m * np.sqrt(np.clip(1.0 - axis * axis, 0.0, 1.0))
        return np.minimum(self.a, self.b) - reach, np.maximum(self.a, self.b) + reach


@dataclass(frozen=True, kw_only=True, eq=False)
class BoxBody(Body):
    """Oriented box: ``center``, ``half_extents_m`` (3,), ``rotation`` (own->world).

    A thin box stands for a plane of finite extent (a torso front, a wall).
    """

    curved: ClassVar[bool] = False

    center: FloatArray
    half_extents_m: FloatArray
    rotation: FloatArray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "center", _frozen_vec(self.center, "center"))
        half = _frozen_vec(self.half_extents_m, "half_extents_m")
        if np.any(half <= 0):
            raise InputError(f"half_extents_m = {half.tolist()}: must be positive")
        object.__setattr__(self, "half_extents_m", half)
        object.__setattr__(self, "rotation", _rotation(self.rotation))

    def shape_key(self) -> tuple:
        return _key("box", self.center, self.half_extents_m, self.rotation)

    def _closest_rest(self, p: FloatArray, noise: float) -> tuple[FloatArray, FloatArray, float]:
        q = (p - self.center) @ self.rotation
        half = self.half_extents_m
        excess = np.abs(q) - half
        sign = np.where(q < 0, -1.0, 1.0)
        if np.any(excess > 0):
            x = np.clip(q, -half, half)
            gap = q - x
            dist = float(np.linalg.norm(gap))
            if dist > noise:
                n_local = gap / dist
            else:  # on the surface within round-off: the normal of the face it is out of most
                i = int(np.argmax(excess))
                n_local = np.zeros(3)
                n_local[i] = sign[i]
        else:  # inside or on the surface: the nearest face
            i = int(np.argmax(excess))
            x = q.copy()
            x[i] = sign[i] * half[i]
            n_local = np.zeros(3)
            n_local[i] = sign[i]
            dist = float(excess[i])
        return self.center + self.rotation @ x, self.rotation @ n_local, dist

    def _intersect_rest(self, o: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
        return raycast.ray_box(o, d, self.center, self.half_extents_m, self.rotation)

    def _mesh_rest(self, tolerance_m: float) -> tuple[FloatArray, IndexArray]:
        return meshing.box_mesh(self.center, self.half_extents_m, self.rotation)

    def _bounds_rest(self) -> tuple[FloatArray, FloatArray]:
        reach = np.abs(self.rotation) @ self.half_extents_m
        return self.center - reach, self.center + reach
