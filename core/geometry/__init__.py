"""Geometry: primitive solids and the robust fits (plane, circle, sphere, quadric) under Alg. 2."""

from .primitives import Box, Capsule, Primitive, Sphere, inside_any

__all__ = ["Box", "Capsule", "Primitive", "Sphere", "inside_any"]
