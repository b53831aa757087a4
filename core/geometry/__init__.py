"""Geometry: primitive solids and the robust fits (plane, circle, sphere, quadric) under Alg. 2."""

from .fits import CircleFit, PlaneFit, SphereFit, circle3d, plane3d, sphere3d
from .primitives import Box, Capsule, Primitive, Sphere, inside_any
from .quadric import QUADRIC_MODELS, QuadricPatch, quadric_patch
from .rotations import orient_normal, orthonormal_frame, rotation_between

__all__ = [
    "QUADRIC_MODELS",
    "Box",
    "Capsule",
    "CircleFit",
    "PlaneFit",
    "Primitive",
    "QuadricPatch",
    "Sphere",
    "SphereFit",
    "circle3d",
    "inside_any",
    "orient_normal",
    "orthonormal_frame",
    "plane3d",
    "quadric_patch",
    "rotation_between",
    "sphere3d",
]
