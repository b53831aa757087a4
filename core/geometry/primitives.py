"""Primitive solids attached to robot links: vectorised inside-tests and signed distances.

The crop stage removes every point inside one of these (grown by a noise margin); the simulator
uses the same shapes as occluders, so the robot removed is the robot seen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..validation import as_finite_scalar, as_points, as_vector3, read_only_copy

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def _positive(value: object, name: str) -> float:
    out = as_finite_scalar(value, name)
    if out <= 0:
        raise InputError(f"{name} = {out}: must be positive")
    return out


@dataclass(frozen=True)
class Sphere:
    """Solid sphere. ``center`` (3,) in m, ``radius`` in m."""

    center: FloatArray
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", read_only_copy(as_vector3(self.center, "center")))
        object.__setattr__(self, "radius", _positive(self.radius, "radius"))

    def signed_distance(self, points: ArrayLike) -> FloatArray:
        """Distance to the surface, negative inside (m), for ``(N, 3)`` points."""
        p = as_points(points, "points")
        return np.linalg.norm(p - self.center, axis=1) - self.radius

    def contains(self, points: ArrayLike, margin_m: float = 0.0) -> BoolArray:
        """True for points inside the sphere grown by ``margin_m``."""
        p = as_points(points, "points")
        d = p - self.center
        reach = self.radius + margin_m
        return np.einsum("ij,ij->i", d, d) < reach * reach

    def translated(self, offset: ArrayLike) -> Sphere:
        return Sphere(self.center + as_vector3(offset, "offset"), self.radius)


@dataclass(frozen=True)
class Capsule:
    """Segment ``a``-``b`` swept by a ball of ``radius`` (m): a link with rounded ends."""

    a: FloatArray
    b: FloatArray
    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "a", read_only_copy(as_vector3(self.a, "a")))
        object.__setattr__(self, "b", read_only_copy(as_vector3(self.b, "b")))
        object.__setattr__(self, "radius", _positive(self.radius, "radius"))

    def _axis_distance(self, p: FloatArray) -> FloatArray:
        ab = self.b - self.a
        length2 = float(ab @ ab)
        ap = p - self.a
        if length2 <= 1e-24:  # a degenerate capsule is a sphere at a
            return np.sqrt(np.einsum("ij,ij->i", ap, ap))
        s = np.clip(ap @ ab / length2, 0.0, 1.0)
        diff = ap - s[:, None] * ab
        return np.sqrt(np.einsum("ij,ij->i", diff, diff))

    def signed_distance(self, points: ArrayLike) -> FloatArray:
        return self._axis_distance(as_points(points, "points")) - self.radius

    def contains(self, points: ArrayLike, margin_m: float = 0.0) -> BoolArray:
        return self._axis_distance(as_points(points, "points")) < self.radius + margin_m

    def translated(self, offset: ArrayLike) -> Capsule:
        off = as_vector3(offset, "offset")
        return Capsule(self.a + off, self.b + off, self.radius)


@dataclass(frozen=True)
class Box:
    """Oriented box: ``center`` (3,), ``half_extents`` (3,) in m, ``rotation`` box-to-world."""

    center: FloatArray
    half_extents: FloatArray
    rotation: FloatArray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", read_only_copy(as_vector3(self.center, "center")))
        half = as_vector3(self.half_extents, "half_extents")
        if np.any(half <= 0):
            raise InputError(f"half_extents = {half.tolist()}: must be positive")
        object.__setattr__(self, "half_extents", read_only_copy(half))
        rot = np.asarray(self.rotation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise InputError(f"rotation: expected a finite (3, 3) matrix, got shape {rot.shape}")
        if not np.allclose(rot.T @ rot, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
            raise InputError("rotation: must be a proper rotation matrix (orthonormal, det +1)")
        object.__setattr__(self, "rotation", read_only_copy(rot))

    def _local(self, points: ArrayLike) -> FloatArray:
        return (as_points(points, "points") - self.center) @ self.rotation

    def signed_distance(self, points: ArrayLike) -> FloatArray:
        q = np.abs(self._local(points)) - self.half_extents
        outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
        inside = np.minimum(q.max(axis=1), 0.0)
        return outside + inside

    def contains(self, points: ArrayLike, margin_m: float = 0.0) -> BoolArray:
        if margin_m == 0.0:
            return np.all(np.abs(self._local(points)) < self.half_extents, axis=1)
        return self.signed_distance(points) < margin_m

    def translated(self, offset: ArrayLike) -> Box:
        return Box(self.center + as_vector3(offset, "offset"), self.half_extents, self.rotation)


Primitive = Sphere | Capsule | Box


def inside_any(
    points: FloatArray, primitives: tuple[Primitive, ...] | list[Primitive], margin_m: float = 0.0
) -> BoolArray:
    """True for points inside any of ``primitives`` grown by ``margin_m``."""
    mask = np.zeros(len(points), dtype=bool)
    for prim in primitives:
        if not isinstance(prim, Sphere | Capsule | Box):
            raise InputError(f"exclude: expected Sphere, Capsule or Box, got {type(prim).__name__}")
        mask |= prim.contains(points, margin_m)
    return mask
