"""Intel RealSense depth cameras through ``pyrealsense2`` (an optional extra).

.. warning::
   UNTESTED AGAINST HARDWARE. This module was written against the documented ``pyrealsense2`` API
   (pipeline, config, ``try_wait_for_frames``, depth scale, stream intrinsics) but has never run
   on a device or a ``.bag`` file in this project's CI; only the missing-module error is tested.

``pyrealsense2`` is imported inside :func:`open_realsense`, so the rest of hapticloud works
without it; choosing the kind without it installed raises
``SourceError("realsense: pyrealsense2 is not installed (pip install pyrealsense2)")``.

Two modes: a live device (``serial=`` picks one, else the first found) or playback of a
``.bag`` recording (``bag=``). The z16 depth stream is converted to float32 metres with the
device's depth scale; intrinsics come from the depth stream profile (no distortion model is kept:
the D4xx depth stream is rectified). Frames are stamped with the device timestamp in s and posed
with the given ``pose_world_camera`` (identity if None).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from hapticloud.core.camera import CameraIntrinsics, DepthFrame
from hapticloud.core.config import StageConfig, param
from hapticloud.core.errors import SourceError
from numpy.typing import ArrayLike

from .base import CameraSource

__all__ = ["RealSenseCameraSource", "RealSenseConfig", "open_realsense"]

MISSING_MESSAGE = "realsense: pyrealsense2 is not installed (pip install pyrealsense2)"


@dataclass(frozen=True)
class RealSenseConfig(StageConfig):
    """Depth stream of one RealSense camera (ignored for ``.bag`` playback, which has its own)."""

    _path: ClassVar[str] = "sources.realsense"

    width: int = param(848, lo=1, hi=1280, unit="px", doc="depth stream width")
    height: int = param(480, lo=1, hi=720, unit="px", doc="depth stream height")
    fps: int = param(30, lo=6, hi=300, unit="Hz", doc="depth stream frame rate")


def _import_rs() -> Any:
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError:
        raise SourceError(MISSING_MESSAGE) from None


class RealSenseCameraSource(CameraSource):
    """One RealSense pipeline (live or ``.bag``) delivering depth frames in metres.

    Use :func:`open_realsense` (or ``open_source("realsense", ...)``) to make one.
    """

    def __init__(
        self,
        rs: Any,
        pipeline: Any,
        profile: Any,
        name: str,
        pose_world_camera: ArrayLike | None = None,
    ) -> None:
        super().__init__()
        self._rs = rs
        self._pipeline = pipeline
        self._name = name
        self._pose = (
            np.eye(4) if pose_world_camera is None else np.asarray(pose_world_camera, float)
        )
        if self._pose.shape != (4, 4):
            raise SourceError(f"{name}: pose_world_camera: expected 4x4, got {self._pose.shape}")
        self._depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
        vp = profile.get_stream(rs.stream.depth).as_video_stream_profile()
        k = vp.get_intrinsics()
        self._intrinsics = CameraIntrinsics(
            int(k.width), int(k.height), float(k.fx), float(k.fy), float(k.ppx), float(k.ppy)
        )

    @property
    def name(self) -> str:
        return self._name

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._intrinsics

    @property
    def depth_scale(self) -> float:
        """Metres per z16 depth unit (device property, typically 0.001)."""
        return self._depth_scale

    def _read(self, timeout: float) -> DepthFrame | None:
        try:
            ok, frames = self._pipeline.try_wait_for_frames(int(timeout * 1000))
        except RuntimeError as exc:
            raise SourceError(f"{self._name}: {exc}") from None
        if not ok:
            return None
        depth = frames.get_depth_frame()
        if not depth:
            return None
        raw = np.asanyarray(depth.get_data())
        depth_m = raw.astype(np.float32) * np.float32(self._depth_scale)
        return DepthFrame(
            float(depth.get_timestamp()) / 1000.0,
            self._name,
            depth_m,
            self._intrinsics,
            self._pose.copy(),
        )

    def _close(self) -> None:
        try:
            self._pipeline.stop()
        except RuntimeError:
            pass


def open_realsense(
    *,
    serial: str | None = None,
    bag: str | Path | None = None,
    name: str | None = None,
    pose_world_camera: ArrayLike | None = None,
    config: RealSenseConfig | None = None,
    repeat_playback: bool = False,
    realtime_playback: bool = True,
) -> RealSenseCameraSource:
    """Registry factory: a live RealSense (``serial=``, or the first device) or ``bag=`` playback.

    Raises :class:`SourceError` if ``pyrealsense2`` is missing, the file does not exist, or the
    pipeline cannot start. Untested against hardware (see the module docstring).
    """
    rs = _import_rs()
    if serial is not None and bag is not None:
        raise SourceError("realsense: give serial= or bag=, not both")
    cfg = config if config is not None else RealSenseConfig()
    rs_config = rs.config()
    if bag is not None:
        path = Path(bag)
        if not path.is_file():
            raise SourceError(f"realsense: bag = {str(path)!r}: no such file")
        rs_config.enable_device_from_file(str(path), repeat_playback=repeat_playback)
        rs_config.enable_stream(rs.stream.depth)
    else:
        if serial is not None:
            rs_config.enable_device(str(serial))
        rs_config.enable_stream(rs.stream.depth, cfg.width, cfg.height, rs.format.z16, cfg.fps)
    pipeline = rs.pipeline()
    try:
        profile = pipeline.start(rs_config)
    except RuntimeError as exc:
        raise SourceError(f"realsense: cannot start pipeline: {exc}") from None
    if bag is not None:
        profile.get_device().as_playback().set_real_time(realtime_playback)
    if name is None:
        name = serial or (Path(bag).stem if bag is not None else "realsense")
    try:
        return RealSenseCameraSource(rs, pipeline, profile, name, pose_world_camera)
    except Exception:
        pipeline.stop()
        raise
