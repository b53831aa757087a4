"""One camera as the perception worker sees it: when it fires, and what it makes of a robot pose.

A :class:`CameraChannel` turns "the robot is here now" into a
:class:`~hapticloud.core.perception.SurfaceEstimate` (and the depth frame it came from, if any).
It does not keep time, admit estimates or choose occluders: the worker
(:class:`~.worker.PerceptionWorker`) does, once for every camera.

- :class:`RenderedChannel`: a simulated depth camera (a stepping
  :class:`~hapticloud.hardware.sources.SimulatedCameraSource` from the registry) rendered at the
  time and with the occluders the worker gives, cropped around the HIP, then its
  :class:`~hapticloud.core.perception.CameraPipeline`;
- :class:`StreamChannel`: a free-running source (a RealSense, a simulated source in real-time
  mode): each frame as it arrives, then its pipeline;
- an oracle camera (no image, the true closest point with noise) comes with a scene
  (:mod:`.scene`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..sources.base import CameraSource

__all__ = [
    "CameraChannel",
    "Capture",
    "ChannelSpec",
    "RenderedChannel",
    "RobotPose",
    "StreamChannel",
]


class RobotPose(NamedTuple):
    """Where the robot is: ``t`` the :func:`time.monotonic` time it was there (the control tick
    that wrote it), ``hip`` (m, world) and ``q`` (rad; ``None``: no joints known, no links
    occlude)."""

    t: float
    hip: NDArray[np.float64]
    q: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class ChannelSpec:
    """A camera's schedule and admission.

    ``rate_hz`` and ``phase_s``: frame ``m`` is due at scene time ``phase_s + m / rate_hz``
    (ignored by a free-running channel, whose frames come when they come). ``latency_s``: an
    estimate reaches the sinks no earlier than this after its capture (a camera's transport
    delay). ``min_quality`` and ``fuse_fallbacks``: what the loop's fusion admits
    (:func:`hapticloud.core.loop.admit`).
    """

    name: str
    rate_hz: float = 30.0
    phase_s: float = 0.0
    latency_s: float = 0.0
    min_quality: float = 0.0
    fuse_fallbacks: bool = False


class Capture(NamedTuple):
    """What a channel made of one frame: the estimate (its ``t`` still the channel's own), the
    depth frame (``None`` for an oracle), and ``captured``: the :func:`time.monotonic` time of a
    frame whose camera keeps its own time (``None``: the pose's time, the worker's mapping)."""

    estimate: Any
    frame: Any = None
    captured: float | None = None


class CameraChannel(ABC):
    """One camera for the worker (see the module docstring)."""

    #: True: the worker asks every round (:meth:`capture` answers ``None`` without a frame);
    #: False: the worker asks when the spec's schedule says a frame is due.
    free_running = False
    #: Whether the robot's links hide part of what this camera sees (the worker computes them
    #: only for channels that use them).
    sees_occluders = True

    def __init__(self, spec: ChannelSpec) -> None:
        self.spec = spec

    @property
    def name(self) -> str:
        return self.spec.name

    @abstractmethod
    def capture(
        self, t_scene: float, pose: RobotPose, occluders: Sequence[Any], full_frame: bool
    ) -> Capture | None:
        """The estimate at scene time ``t_scene`` with the robot at ``pose`` and ``occluders``
        in front of the world (rendered whole when ``full_frame``: a recorder keeps more than
        the crop reads)."""

    @abstractmethod
    def close(self) -> None:
        """Release what the channel holds (its source)."""


class RenderedChannel(CameraChannel):
    """A simulated camera rendered on the worker's schedule (see the module docstring).

    ``source``: a :class:`~hapticloud.hardware.sources.SimulatedCameraSource` in stepping mode
    (``open_source("simulated", ..., realtime=False)``); ``pipeline``: its
    :class:`~hapticloud.core.perception.CameraPipeline`.
    """

    def __init__(self, spec: ChannelSpec, source: Any, pipeline: Any) -> None:
        super().__init__(spec)
        self.source = source
        self.pipeline = pipeline

    def capture(
        self, t_scene: float, pose: RobotPose, occluders: Sequence[Any], full_frame: bool
    ) -> Capture:
        # Only the pixels the crop reads are ray-cast, unless a sink keeps the whole frame.
        roi = None if full_frame else self.source.camera.workspace_roi(pose.hip, self.crop)
        self.source.capture(t_scene, occluders, roi)
        frame = self.source.read(0.0)  # the source's counters see it
        est = self.pipeline.process_depth(frame, pose.hip, exclude=occluders)
        return Capture(est, frame)

    @property
    def crop(self) -> Any:
        return self.pipeline.config.crop

    def close(self) -> None:
        self.source.close()


class StreamChannel(CameraChannel):
    """A free-running :class:`~hapticloud.hardware.sources.CameraSource` (its own clock) and
    its pipeline: each frame when it arrives, captured at the time the source returned it."""

    free_running = True

    def __init__(self, spec: ChannelSpec, source: CameraSource, pipeline: Any) -> None:
        super().__init__(spec)
        self.source = source
        self.pipeline = pipeline

    def capture(
        self, t_scene: float, pose: RobotPose, occluders: Sequence[Any], full_frame: bool
    ) -> Capture | None:
        frame = self.source.read(0.0)
        if frame is None:
            return None
        est = self.pipeline.process_depth(frame, pose.hip, exclude=occluders)
        return Capture(est, frame, self.source.last_frame_time)

    def close(self) -> None:
        self.source.close()
