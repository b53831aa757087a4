"""One perception worker: cameras against the live robot, estimates to sinks.

:class:`PerceptionWorker` (:mod:`.worker`) owns, for every camera, the schedule, the robot pose
and its occluders, the time mapping onto the control loop's clock and the admission, and hands
each frame's :class:`Perceived` to its sinks: the control loop (:class:`ControlSink`), a display
(:class:`DisplaySink`), a recorder (:class:`RecorderSink`). Cameras are channels
(:mod:`.channels`) over the camera sources of :mod:`hapticloud.hardware.sources`; a scene's
cameras and the control process's robot come from :mod:`.scene`. It runs in the caller's
thread, a thread, or a process (:class:`PerceptionProcess`).
"""

from .channels import CameraChannel, Capture, ChannelSpec, RenderedChannel, RobotPose, StreamChannel
from .process import PerceptionProcess
from .scene import (
    OracleChannel,
    StateBlockFeed,
    link_occluders,
    scene_channels,
    scene_sim,
    session_worker,
)
from .sinks import ControlSink, DisplaySink, Perceived, RecorderSink, Sink
from .worker import FixedPose, FrameSchedule, PerceptionWorker, RobotFeed, no_occluders

__all__ = [
    "CameraChannel",
    "Capture",
    "ChannelSpec",
    "ControlSink",
    "DisplaySink",
    "FixedPose",
    "FrameSchedule",
    "OracleChannel",
    "Perceived",
    "PerceptionProcess",
    "PerceptionWorker",
    "RecorderSink",
    "RenderedChannel",
    "RobotFeed",
    "RobotPose",
    "Sink",
    "StateBlockFeed",
    "StreamChannel",
    "link_occluders",
    "no_occluders",
    "scene_channels",
    "scene_sim",
    "session_worker",
]
