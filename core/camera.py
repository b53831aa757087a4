"""Pin-hole depth cameras: intrinsics, depth frames and (de)projection.

Frames follow the OpenCV convention: camera ``x`` right, ``y`` down, ``z`` along the viewing axis.
``pose_world_camera`` maps camera coordinates to world coordinates (a 4x4 rigid transform).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pin-hole intrinsics in pixels (no distortion: the D435 depth stream is rectified)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise InputError(
                f"intrinsics: width and height must be >= 1, got {self.width}x{self.height}"
            )
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"intrinsics.{name} = {value}: must be a positive number")
        for name in ("cx", "cy"):
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"intrinsics.{name}: must be finite")

    @classmethod
    def d435(cls, width: int = 848, height: int = 480, hfov_deg: float = 87.0) -> CameraIntrinsics:
        """D435-like depth intrinsics (87 deg horizontal field of view, square pixels)."""
        fx = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(width, height, fx, fx, (width - 1) / 2.0, (height - 1) / 2.0)

    def pixel_rays(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """Per-pixel ``(x/z, y/z)`` grids of shape ``(height, width)``, cached."""
        return _pixel_rays(self)


_RAY_CACHE: dict[CameraIntrinsics, tuple[NDArray[np.float32], NDArray[np.float32]]] = {}


def _pixel_rays(k: CameraIntrinsics) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    rays = _RAY_CACHE.get(k)
    if rays is None:
        u = (np.arange(k.width, dtype=np.float64) - k.cx) / k.fx
        v = (np.arange(k.height, dtype=np.float64) - k.cy) / k.fy
        xs = np.broadcast_to(u[None, :], (k.height, k.width)).astype(np.float32)
        ys = np.broadcast_to(v[:, None], (k.height, k.width)).astype(np.float32)
        xs.setflags(write=False)
        ys.setflags(write=False)
        rays = _RAY_CACHE[k] = (xs, ys)
    return rays


_Z_UP = (0.0, 0.0, 1.0)


def look_at(eye: NDArray, target: NDArray, up: NDArray | tuple = _Z_UP) -> FloatArray:
    """``pose_world_camera`` of a camera at ``eye`` looking at ``target`` (image ``y`` down)."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
    return pose


@dataclass(frozen=True)
class DepthFrame:
    """One depth image with everything needed to put its pixels in the world.

    ``depth_m`` is ``(height, width)`` float32 metres along the viewing axis; 0 or NaN is invalid.
    """

    t: float
    camera: str
    depth_m: NDArray[np.float32]
    intrinsics: CameraIntrinsics
    pose_world_camera: FloatArray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        depth = np.asarray(self.depth_m)
        k = self.intrinsics
        if depth.shape != (k.height, k.width):
            raise InputError(
                f"depth_m: expected shape ({k.height}, {k.width}) from the intrinsics, "
                f"got {depth.shape}"
            )
        if not np.issubdtype(depth.dtype, np.floating):
            raise InputError(f"depth_m: expected a float image in metres, got dtype {depth.dtype}")
        pose = np.asarray(self.pose_world_camera, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise InputError(
                f"pose_world_camera: expected a finite 4x4 transform, got {pose.shape}"
            )
        object.__setattr__(self, "pose_world_camera", pose)

    @property
    def axis_world(self) -> FloatArray:
        """The camera's viewing axis (its ``z``) in the world frame."""
        return self.pose_world_camera[:3, 2].copy()

    @property
    def origin_world(self) -> FloatArray:
        """The camera's optical centre in the world frame."""
        return self.pose_world_camera[:3, 3].copy()

    def points_camera(
        self, rows: slice = slice(None), cols: slice = slice(None)
    ) -> NDArray[np.float32]:
        """Valid pixels of the region ``[rows, cols]`` as ``(N, 3)`` float32 in the camera frame."""
        xs, ys = self.intrinsics.pixel_rays()
        z = self.depth_m[rows, cols]
        valid = np.isfinite(z) & (z > 0)
        zv = z[valid]
        return np.stack((xs[rows, cols][valid] * zv, ys[rows, cols][valid] * zv, zv), axis=1)

    def points_world(self, rows: slice = slice(None), cols: slice = slice(None)) -> FloatArray:
        """Valid pixels of the region ``[rows, cols]`` as ``(N, 3)`` float64 in the world frame."""
        pc = self.points_camera(rows, cols).astype(np.float64)
        rot, trans = self.pose_world_camera[:3, :3], self.pose_world_camera[:3, 3]
        return pc @ rot.T + trans
