"""Synthetic depth-camera patches of body-like surfaces with a known closest point (test helper).

A camera about 0.7 m away casts a regular grid of rays (about one per ``spacing_m`` on the surface,
like a voxel-filtered cloud) at an analytic surface: a head-sized sphere, an ellipsoid, an
arm-sized cylinder or a tilted torso plane. The HIP sits ``hip_distance_m`` above a surface point
whose normal is within ``max_tilt_deg`` of the direction facing the camera, so that point is the
true closest point (the surfaces are convex). Depth noise is Gaussian along each ray with
``sigma = 0.5 mm + 2 mm * depth²`` (depth in m); an optional disc around the true closest point is
hidden (the end effector occludes it); optional flying pixels are moved 1-5 cm along their ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

SHAPES = ("sphere", "ellipsoid", "cylinder", "plane")
HEAD_RADIUS_M = 0.09
ELLIPSOID_AXES_M = (0.075, 0.095, 0.11)
ARM_RADIUS_M = 0.045


@dataclass(frozen=True)
class Patch:
    """One synthetic frame: the cloud, the HIP and the ground truth (world frame, m)."""

    shape: str
    points: FloatArray
    hip: FloatArray
    camera_axis: FloatArray
    camera_position: FloatArray
    closest: FloatArray
    normal: FloatArray
    distance_m: float


def _unit(v: FloatArray) -> FloatArray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _basis(axis: FloatArray) -> tuple[FloatArray, FloatArray]:
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    e1 = _unit(np.cross(axis, helper))
    return e1, np.cross(axis, e1)


def _random_rotation(rng: np.random.Generator) -> FloatArray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _direction_in_cone(rng: np.random.Generator, axis: FloatArray, max_deg: float) -> FloatArray:
    """Uniform on the spherical cap of half-angle ``max_deg`` around ``axis``."""
    cos_max = np.cos(np.radians(max_deg))
    cos_t = rng.uniform(cos_max, 1.0)
    phi = rng.uniform(0.0, 2.0 * np.pi)
    e1, e2 = _basis(axis)
    sin_t = np.sqrt(1.0 - cos_t * cos_t)
    return cos_t * axis + sin_t * (np.cos(phi) * e1 + np.sin(phi) * e2)


# ----- surfaces: first ray hit (t, NaN for a miss) ---------------------------------------------


def _quadratic_first_root(a: FloatArray, b: FloatArray, c: FloatArray) -> FloatArray:
    disc = b * b - 4.0 * a * c
    t = np.full(np.shape(b), np.nan)
    ok = (disc >= 0.0) & (np.abs(a) > 1e-15)
    t[ok] = (-b[ok] - np.sqrt(disc[ok])) / (2.0 * a[ok])
    t[t <= 0.0] = np.nan
    return t


def _hit_ellipsoid(origin, dirs, center, rot, axes) -> FloatArray:
    # Map to the unit sphere: x_unit = diag(1/axes) rot^T (x - center).
    o = (rot.T @ (origin - center)) / axes
    d = (dirs @ rot) / axes
    a = np.einsum("ij,ij->i", d, d)
    b = 2.0 * d @ o
    c = np.full(len(d), o @ o - 1.0)
    return _quadratic_first_root(a, b, c)


def _hit_cylinder(origin, dirs, point, axis, radius) -> FloatArray:
    o = origin - point
    o_perp = o - (o @ axis) * axis
    d_perp = dirs - np.outer(dirs @ axis, axis)
    a = np.einsum("ij,ij->i", d_perp, d_perp)
    b = 2.0 * d_perp @ o_perp
    c = np.full(len(dirs), o_perp @ o_perp - radius * radius)
    return _quadratic_first_root(a, b, c)


def _hit_plane(origin, dirs, point, normal) -> FloatArray:
    den = dirs @ normal
    t = np.full(len(dirs), np.nan)
    ok = np.abs(den) > 1e-9
    t[ok] = ((point - origin) @ normal) / den[ok]
    t[t <= 0.0] = np.nan
    return t


def make_patch(
    shape: str,
    rng: np.random.Generator,
    *,
    hip_distance_m: float | None = None,
    hole_radius_m: float = 0.0,
    outlier_fraction: float = 0.0,
    spacing_m: float = 0.003,
    crop_radius_m: float = 0.15,
    camera_distance_m: float = 0.7,
    max_tilt_deg: float = 45.0,
    noise: bool = True,
    offset: FloatArray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    camera_axis: FloatArray | None = None,
) -> Patch:
    """Generate one synthetic patch.

    Parameters
    ----------
    shape
        ``"sphere"`` (R 0.09 m), ``"ellipsoid"`` (0.075 x 0.095 x 0.11 m, random orientation),
        ``"cylinder"`` (r 0.045 m, axis at least 45° from the view) or ``"plane"``.
    rng
        Source of randomness (seed it: the tests are deterministic).
    hip_distance_m
        HIP-surface distance (m); default uniform in [0.04, 0.11].
    hole_radius_m
        Points closer than this to the true closest point are hidden (0: none).
    outlier_fraction
        Fraction of points moved 1-5 cm along their ray, either way (flying pixels).
    spacing_m
        Ray spacing on a surface facing the camera at the closest point's depth (m).
    crop_radius_m
        Only points within this distance of the HIP are returned.
    camera_distance_m
        Distance from the camera to the shape's centre (plane: to the plane) (m).
    max_tilt_deg
        Largest angle between the true normal and the direction facing the camera.
    noise
        False gives exact points (no depth noise).
    offset
        Added to everything (m): moves the scene far from the origin.
    camera_axis
        Viewing direction; default random.
    """
    if shape not in SHAPES:
        raise ValueError(f"shape = {shape!r}: must be one of {', '.join(SHAPES)}")
    off = np.asarray(offset, dtype=np.float64)
    if camera_axis is None:
        z_cam = _unit(rng.normal(size=3))
    else:
        z_cam = _unit(np.asarray(camera_axis, dtype=np.float64))
    cam = np.zeros(3)
    center = cam + camera_distance_m * z_cam
    facing = -z_cam
    n_true = _direction_in_cone(rng, facing, max_tilt_deg)
    if shape == "sphere":
        rot, axes = np.eye(3), np.full(3, HEAD_RADIUS_M)
        q = center + HEAD_RADIUS_M * n_true
        hit = lambda o, d: _hit_ellipsoid(o, d, center, rot, axes)  # noqa: E731
    elif shape == "ellipsoid":
        rot, axes = _random_rotation(rng), np.array(ELLIPSOID_AXES_M)
        m_inv = rot @ np.diag(axes**2) @ rot.T  # inverse of the quadric's matrix
        q = center + m_inv @ n_true / np.sqrt(n_true @ m_inv @ n_true)
        hit = lambda o, d: _hit_ellipsoid(o, d, center, rot, axes)  # noqa: E731
    elif shape == "cylinder":
        # Axis at least 45° from the view: an arm seen from the side or obliquely.
        while True:
            axis = _unit(rng.normal(size=3))
            if abs(axis @ z_cam) < np.cos(np.radians(45.0)):
                break
        # Normal: orthogonal to the axis, within the tilt cone around the facing direction.
        e1 = _unit(facing - (facing @ axis) * axis)
        e2 = np.cross(axis, e1)
        lim = np.radians(max_tilt_deg)
        for _ in range(100):
            ang = rng.uniform(-lim, lim)
            n_true = np.cos(ang) * e1 + np.sin(ang) * e2
            if n_true @ facing >= np.cos(lim):
                break
        else:
            n_true = e1
        q = center + ARM_RADIUS_M * n_true + rng.uniform(-0.05, 0.05) * axis
        hit = lambda o, d: _hit_cylinder(o, d, center, axis, ARM_RADIUS_M)  # noqa: E731
    else:
        q = center + rng.uniform(-0.05, 0.05, size=3)
        q -= ((q - center) @ n_true) * n_true  # on the plane through ``center``
        hit = lambda o, d: _hit_plane(o, d, center, n_true)  # noqa: E731
    dist = rng.uniform(0.04, 0.11) if hip_distance_m is None else float(hip_distance_m)
    hip = q + dist * n_true

    # A jittered grid of rays covering the crop ball around the HIP.
    to_hip = hip - cam
    half = np.arcsin(min(0.99, crop_radius_m / np.linalg.norm(to_hip))) + 0.02
    step = spacing_m / ((q - cam) @ z_cam)
    e1, e2 = _basis(z_cam)
    aim = _unit(to_hip)
    tan_h = np.tan(half)
    grid = np.arange(-tan_h, tan_h, step) + rng.uniform(0.0, step)
    u, v = np.meshgrid(grid, grid)
    u = u.ravel() + rng.uniform(-0.25, 0.25, u.size) * step
    v = v.ravel() + rng.uniform(-0.25, 0.25, v.size) * step
    # Aim the grid at the HIP: a pinhole's rays through the patch, evenly spread.
    a1, a2 = _basis(aim)
    dirs = _unit(aim + u[:, None] * a1 + v[:, None] * a2)
    t = hit(cam, dirs)
    ok = np.isfinite(t)
    dirs, t = dirs[ok], t[ok]
    clean = cam + t[:, None] * dirs
    keep = np.linalg.norm(clean - hip, axis=1) < crop_radius_m + 0.01
    if hole_radius_m > 0.0:
        keep &= np.linalg.norm(clean - q, axis=1) >= hole_radius_m
    dirs, t = dirs[keep], t[keep]
    if noise:
        depth = t * (dirs @ z_cam)
        t = t + rng.normal(size=len(t)) * (0.0005 + 0.002 * depth * depth)
    if outlier_fraction > 0.0 and len(t):
        n_out = round(outlier_fraction * len(t))
        idx = rng.choice(len(t), size=n_out, replace=False)
        t[idx] += rng.choice([-1.0, 1.0], size=n_out) * rng.uniform(0.01, 0.05, size=n_out)
    pts = cam + t[:, None] * dirs
    pts = pts[np.linalg.norm(pts - hip, axis=1) < crop_radius_m]
    pts = pts[rng.permutation(len(pts))]
    return Patch(
        shape=shape,
        points=pts + off,
        hip=hip + off,
        camera_axis=z_cam,
        camera_position=cam + off,
        closest=q + off,
        normal=n_true,
        distance_m=dist,
    )
