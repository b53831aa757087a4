"""A recorded camera frame: the stored pixels, and what the pipeline needs besides them.

A recording keeps, per camera frame, the rectangle of the depth image that the perception crop
could read (the workspace sphere's :func:`~hapticloud.core.perception.crop.sphere_region`,
grown by :attr:`RecordConfig.roi_margin_px` and, for re-runs with a larger workspace, by
:attr:`RecordConfig.roi_radius_scale`), the HIP at capture and the robot's exclusion shapes. A
full-size frame rebuilt from it (zeros outside the rectangle: the "no depth" value) gives the
pipeline exactly the pixels it read when recording, so a re-run with the recording's own
parameters reproduces its estimates bit for bit.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..camera import CameraIntrinsics, DepthFrame
from ..config import StageConfig, param
from ..errors import ConfigError, InputError
from ..geometry import Box, Capsule, Primitive, Sphere
from ..perception.config import CropConfig
from ..perception.crop import sphere_region

FloatArray = NDArray[np.float64]
Window = tuple[int, int, int, int]


@dataclass(frozen=True)
class RecordConfig(StageConfig):
    """What a recording stores and how often it makes its file safe."""

    frames: str = param(
        "roi",
        choices=("roi", "full"),
        doc="roi: the pixels the workspace crop can read (about 9x smaller); full: every pixel",
    )
    roi_margin_px: int = param(
        4, lo=0, hi=64, unit="px", doc="pixels kept around the crop's rectangle on every side"
    )
    roi_radius_scale: float = param(
        1.0,
        lo=1.0,
        hi=3.0,
        unit="",
        doc="store the rectangle of a workspace sphere this many times the crop's radius",
    )
    flush_period_s: float = param(
        0.5,
        lo=0.05,
        hi=1.0,
        unit="s",
        doc="the file holds everything older than this after a crash (a chunk closed and flushed)",
    )
    queue_messages: int = param(
        2048, lo=16, hi=100000, doc="messages waiting for the recorder before new ones are dropped"
    )


def storage_roi(
    frame: DepthFrame, hip: FloatArray, crop: CropConfig, config: RecordConfig
) -> Window:
    """``(row0, row1, col0, col1)`` of ``frame`` to store (half-open; the whole image for
    ``frames = "full"``; ``(0, 0, 0, 0)`` when the workspace is out of view)."""
    k = frame.intrinsics
    if config.frames == "full":
        return (0, k.height, 0, k.width)
    radius = crop.workspace_radius_m * config.roi_radius_scale
    found = sphere_region(frame, hip, radius, crop.min_depth_m, crop.max_depth_m)
    if found is None:
        return (0, 0, 0, 0)
    m = config.roi_margin_px
    r0, r1, c0, c1 = found[:4]
    return (max(0, r0 - m), min(k.height, r1 + m), max(0, c0 - m), min(k.width, c1 + m))


def frame_from_roi(
    t: float,
    camera: str,
    pixels: NDArray[np.float32],
    roi: Sequence[int],
    intrinsics: CameraIntrinsics,
    pose_world_camera: FloatArray,
) -> DepthFrame:
    """The full-size frame of a stored rectangle: its pixels at ``roi``, 0 (no depth) elsewhere."""
    r0, r1, c0, c1 = (int(v) for v in roi)
    if not (0 <= r0 <= r1 <= intrinsics.height and 0 <= c0 <= c1 <= intrinsics.width):
        raise InputError(
            f"roi = {list(roi)}: outside the {intrinsics.width}x{intrinsics.height} image"
        )
    pixels = np.asarray(pixels)
    if pixels.shape != (r1 - r0, c1 - c0):
        raise InputError(
            f"pixels: expected shape {(r1 - r0, c1 - c0)} for roi {list(roi)}, got {pixels.shape}"
        )
    depth = np.zeros((intrinsics.height, intrinsics.width), dtype=np.float32)
    depth[r0:r1, c0:c1] = pixels
    return DepthFrame(float(t), camera, depth, intrinsics, pose_world_camera)


def roi_covers(frame: DepthFrame, hip: FloatArray, crop: CropConfig, roi: Sequence[int]) -> bool:
    """Whether the crop of ``crop`` around ``hip`` reads only pixels inside the stored ``roi``."""
    found = sphere_region(frame, hip, crop.workspace_radius_m, crop.min_depth_m, crop.max_depth_m)
    if found is None:
        return True
    r0, r1, c0, c1 = found[:4]
    return roi[0] <= r0 and r1 <= roi[1] and roi[2] <= c0 and c1 <= roi[3]


@dataclass(frozen=True)
class CapturedFrame:
    """One recorded camera frame with what the pipeline needs besides the pixels.

    ``frame`` is full-size (see :func:`frame_from_roi`), ``roi`` the stored rectangle, ``hip``
    the HIP at capture (m, world), ``exclude`` the robot's shapes then, ``seq`` the sequence
    number of the estimate recorded for this frame and ``log_time_s`` its time in the recording.
    """

    frame: DepthFrame
    roi: Window
    hip: FloatArray
    exclude: tuple[Primitive, ...]
    seq: int
    log_time_s: float

    @property
    def camera(self) -> str:
        return self.frame.camera


def _vec(data: Mapping[str, Any], key: str) -> list[float]:
    return [float(x) for x in np.asarray(data[key], dtype=np.float64).reshape(-1)]


def primitive_to_dict(prim: Primitive) -> dict[str, Any]:
    """A JSON-ready dict of an exclusion shape (exact: floats round-trip through JSON)."""
    if isinstance(prim, Capsule):
        return {
            "type": "capsule",
            "a": [float(x) for x in prim.a],
            "b": [float(x) for x in prim.b],
            "radius": float(prim.radius),
        }
    if isinstance(prim, Sphere):
        return {"type": "sphere", "center": [float(x) for x in prim.center], "radius": prim.radius}
    if isinstance(prim, Box):
        return {
            "type": "box",
            "center": [float(x) for x in prim.center],
            "half_extents": [float(x) for x in prim.half_extents],
            "rotation": [[float(x) for x in row] for row in prim.rotation],
        }
    raise InputError(f"exclude: cannot record a {type(prim).__name__}")


def primitive_from_dict(data: Mapping[str, Any]) -> Primitive:
    """The shape of :func:`primitive_to_dict`'s dict (``ConfigError`` naming what is wrong)."""
    kind = data.get("type")
    try:
        if kind == "capsule":
            return Capsule(_vec(data, "a"), _vec(data, "b"), float(data["radius"]))
        if kind == "sphere":
            return Sphere(_vec(data, "center"), float(data["radius"]))
        if kind == "box":
            return Box(
                _vec(data, "center"),
                _vec(data, "half_extents"),
                np.asarray(data["rotation"], dtype=np.float64),
            )
    except (KeyError, TypeError, ValueError) as err:
        raise ConfigError(f"exclude: a {kind} without a valid {err}") from None
    raise ConfigError(f"exclude: unknown shape type {kind!r}")


__all__ = [
    "CapturedFrame",
    "RecordConfig",
    "frame_from_roi",
    "primitive_from_dict",
    "primitive_to_dict",
    "roi_covers",
    "storage_roi",
]
