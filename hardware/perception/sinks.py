"""Where the perception worker's estimates go: one :class:`Perceived` per frame, to every sink.

- :class:`ControlSink`: the control loop's estimates pipe
  (:attr:`~hapticloud.hardware.control.process.ControlProcess.estimate_connection`), in the one
  estimate wire form (:func:`~hapticloud.hardware.control.messages.send_estimate`);
- :class:`DisplaySink`: a callback or a queue (the live app's display);
- :class:`RecorderSink`: a recorder's
  :class:`~hapticloud.hardware.recording.recorder.RecordSink` (each frame, its HIP and occluders
  and the estimate sent).

A sink's :meth:`~Sink.put` runs in the worker's thread: it must not block for long.
"""

from __future__ import annotations

import queue
import select
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from ..control.messages import send_estimate

__all__ = ["ControlSink", "DisplaySink", "Perceived", "RecorderSink", "Sink"]


@dataclass(frozen=True)
class Perceived:
    """One camera frame, perceived.

    ``estimate`` is the estimate as the control loop fuses it: its ``t`` is ``captured`` (the
    :func:`time.monotonic` time the robot was at ``hip``), its ``seq`` the camera's frame count.
    ``t_scene`` is the scene time the frame was rendered at; ``frame`` the depth frame (``None``
    for an oracle camera); ``occluders`` the robot's shapes that hid part of it and that the
    crop left out; ``admitted`` whether the loop's fusion takes it; ``perception_ms`` what
    rendering and processing took.
    """

    camera: str
    seq: int
    t_scene: float
    captured: float
    estimate: Any
    frame: Any
    hip: NDArray[np.float64]
    q: NDArray[np.float64] | None
    occluders: Any
    admitted: bool
    perception_ms: float


class Sink(Protocol):
    """What the worker hands each :class:`Perceived` to (at its camera's latency after capture).

    ``wants_frames``: the sink keeps whole frames (the worker then renders them uncropped).
    """

    wants_frames: bool

    def put(self, item: Perceived) -> None: ...


class ControlSink:
    """Estimates to the control loop's fusion, down its estimates pipe (any process).

    ``drop_when_full``: an estimate the pipe cannot take now is dropped and counted
    (:attr:`dropped`) instead of waiting for the loop to read (a display that must not stall).
    When the pipe is gone (the control process stopped) the sink goes quiet (:attr:`alive`).
    """

    wants_frames = False

    def __init__(self, conn: Any, *, drop_when_full: bool = False) -> None:
        self._conn = conn
        self._drop_when_full = drop_when_full
        self.alive = True
        self.sent = 0
        self.dropped = 0

    def put(self, item: Perceived) -> None:
        if not self.alive:
            return
        try:
            if self._drop_when_full and not select.select((), (self._conn.fileno(),), (), 0.0)[1]:
                self.dropped += 1
                return
            send_estimate(self._conn, item.estimate)
            self.sent += 1
        except (OSError, ValueError):
            self.alive = False  # the control process is gone: perception goes on alone

    def detach(self) -> None:
        """Send nothing more (the control process is about to stop)."""
        self.alive = False


class DisplaySink:
    """Each :class:`Perceived` to ``target``: a callable, or a queue (``put_nowait``; a full
    queue drops the item and counts it in :attr:`dropped`)."""

    wants_frames = False

    def __init__(self, target: Callable[[Perceived], None] | Any) -> None:
        self._put = target if callable(target) else target.put_nowait
        self.dropped = 0

    def put(self, item: Perceived) -> None:
        try:
            self._put(item)
        except queue.Full:
            self.dropped += 1


class RecorderSink:
    """Each rendered frame, with its HIP, occluders and estimate, to a recorder's
    :class:`~hapticloud.hardware.recording.recorder.RecordSink` at its capture time.
    ``frameless``: an estimate without a frame (an oracle camera) is recorded too."""

    wants_frames = True

    def __init__(self, record_sink: Any, *, frameless: bool = False) -> None:
        self.record_sink = record_sink
        self._frameless = frameless

    def put(self, item: Perceived) -> None:
        if item.frame is not None:
            self.record_sink.capture(
                item.captured, item.frame, item.hip, item.occluders, item.estimate
            )
        elif self._frameless:
            self.record_sink.estimate(item.captured, item.estimate)

    @property
    def dropped(self) -> int:
        """Items the recorder's queue could not take."""
        return int(self.record_sink.dropped)
