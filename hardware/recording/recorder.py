"""The recorder: a low-priority process that writes what the session's processes send it.

Producers (the run's own process, the perception process) hold a :class:`RecordSink`: each call
puts one small tuple on a bounded ``multiprocessing`` queue with ``put_nowait`` and returns (a
full queue drops the message and counts it; a producer never waits for the disk). The control
process never records anything itself: its snapshots reach the recorder through the parent,
which drains them anyway. The recorder process (:func:`_recorder_main`, ``nice`` +10) encodes,
compresses and writes with :class:`~.writer.RecordingWriter`, closing a chunk at least every
``flush_period_s``.

A write that fails (``ENOSPC``: the disk is full, or any ``OSError``) stops the recording, not
the session: the recorder leaves the file with its whole chunks (readable, unfinished), keeps
draining the queue so the producers never notice, and sends an alarm the session shows
(:meth:`Recorder.alarms`) and reports (:meth:`Recorder.close`'s ``error``).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import time
import traceback
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from hapticloud.core.camera import CameraIntrinsics, DepthFrame
from hapticloud.core.errors import RecordingError
from hapticloud.core.perception.config import CropConfig
from hapticloud.core.recording import RecordConfig, primitive_to_dict, storage_roi

#: ``nice`` value of the recorder process: writing gives way to perception and the GUI.
RECORDER_NICE = 10
_STOP = ("stop",)


@dataclass(frozen=True)
class FrameHeader:
    """What the writer reads of a frame besides its pixels (time, camera, intrinsics, pose):
    pickled in a few hundred bytes, where a full-size frame, even a zero-stride one, pickles as
    its 1.6 MB of pixels."""

    t: float
    camera: str
    intrinsics: CameraIntrinsics
    pose_world_camera: Any


@dataclass(frozen=True)
class CutFrame:
    """A frame cut for the recorder: its header, the stored rectangle ``roi`` and its pixels,
    the HIP, the robot's shapes (dicts), the estimate's wire dict and its ``seq``."""

    header: FrameHeader
    roi: tuple[int, int, int, int]
    pixels: Any
    hip: list[float]
    shapes: list[dict[str, Any]]
    estimate: dict[str, Any]

    @property
    def seq(self) -> int:
        return int(self.estimate["seq"])


def cut_frame(
    frame: DepthFrame,
    hip: Any,
    exclude: Sequence[Any],
    estimate: Any,
    crop: CropConfig,
    record: RecordConfig,
) -> CutFrame:
    """Cut ``frame`` to what a recording stores (:func:`storage_roi` of ``crop`` and
    ``record``), with the HIP, the robot's shapes and ``estimate`` in their recorded forms."""
    from ..control.messages import estimate_to_dict

    hip_v = np.asarray(hip, dtype=np.float64)
    roi = storage_roi(frame, hip_v, crop, record)
    r0, r1, c0, c1 = roi
    pixels = np.array(frame.depth_m[r0:r1, c0:c1], dtype=np.float32)
    header = FrameHeader(
        float(frame.t),
        frame.camera,
        frame.intrinsics,
        np.asarray(frame.pose_world_camera, dtype=np.float64),
    )
    shapes = [primitive_to_dict(p) for p in exclude]
    return CutFrame(header, roi, pixels, hip_v.tolist(), shapes, estimate_to_dict(estimate))


class RecordSink:
    """What a producer calls; picklable (pass it to a ``spawn`` child at creation)."""

    def __init__(
        self, q: Any, record: RecordConfig, crop: CropConfig, *, blocking: bool = False
    ) -> None:
        self._q = q
        #: Wait for room instead of dropping (a simulated run, which has no deadline to keep).
        self.blocking = blocking
        self.record = record
        self.crop = crop
        #: Messages this process dropped because the queue was full.
        self.dropped = 0
        self.sent = 0
        #: In the recorder's parent: whether its process lives (a blocking sink waits while it
        #: does: a recorder at nice +10 on a busy machine can be starved for many seconds).
        self.alive: Any = None

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["alive"] = None  # a process handle stays with its parent
        return state

    def _put(self, item: tuple[Any, ...]) -> bool:
        try:
            if self.blocking:
                while True:
                    try:
                        self._q.put(item, timeout=10.0)
                        break
                    except queue.Full:
                        if self.alive is None or not self.alive():
                            raise
            else:
                self._q.put_nowait(item)
        except (queue.Full, ValueError, OSError):  # full, or the recorder is gone
            # A recorder that took nothing for that long is gone: never wait for it again.
            self.blocking = False
            self.dropped += 1
            return False
        self.sent += 1
        return True

    def capture(
        self,
        log_time_s: float,
        frame: DepthFrame,
        hip: Any,
        exclude: Sequence[Any],
        estimate: Any,
    ) -> None:
        """One processed camera frame and its estimate (the rectangle of :class:`RecordConfig`
        is cut here, so only those pixels cross the queue)."""
        self.put_cut(log_time_s, cut_frame(frame, hip, exclude, estimate, self.crop, self.record))

    def put_cut(self, log_time_s: float, cut: CutFrame) -> None:
        """A frame already cut (:func:`cut_frame`, e.g. in another process) and its estimate."""
        self._put(
            ("capture", log_time_s, cut.header, cut.roi, cut.pixels, cut.hip, cut.shapes, cut.seq)
        )
        self._put(("estimate", log_time_s, cut.header.camera, cut.estimate))

    def estimate(self, log_time_s: float, estimate: Any) -> None:
        """An estimate without a frame (an oracle camera)."""
        from ..control.messages import estimate_to_dict

        self._put(("estimate", log_time_s, str(estimate.camera), estimate_to_dict(estimate)))

    def control_state(
        self, log_time_s: float, state: Mapping[str, Any], hip_radius_m: float
    ) -> None:
        self._put(("control_state", log_time_s, dict(state), hip_radius_m))

    def event(self, log_time_s: float, level: str, source: str, text: str) -> None:
        self._put(("event", log_time_s, level, source, text))


def _recorder_main(
    path: str,
    q: Any,
    conn: Any,
    metadata: dict[str, str],
    config_toml: dict[str, str],
    scene: dict[str, str] | None,
    record: RecordConfig,
    limit_bytes: int | None,
) -> None:
    from hapticloud.core.threads import settle_numerics

    from .writer import RecordingWriter, open_recording_file

    settle_numerics(1)
    try:
        os.setpriority(os.PRIO_PROCESS, 0, RECORDER_NICE)  # as is: not added to the app's
    except OSError:
        pass
    try:
        writer = RecordingWriter(
            open_recording_file(path, limit_bytes), metadata, config_toml, scene, record
        )
    except OSError as err:
        conn.send(("error", f"{path}: cannot be written ({err.strerror or err})"))
        return
    conn.send(("ready", None))
    error = ""
    written = 0
    cpu0 = time.process_time()
    period = record.flush_period_s
    while True:
        try:
            item = q.get(timeout=period / 2)
        except queue.Empty:
            item = None
        if item == _STOP:
            break
        if error:
            continue  # the recording stopped: drain, so that the producers never block
        try:
            if item is not None:
                kind = item[0]
                if kind == "capture":
                    _, log_t, frame, roi, pixels, hip, shapes, seq = item
                    writer.capture(log_t, frame, roi, pixels, hip, shapes, seq)
                elif kind == "estimate":
                    writer.estimate(item[1], item[2], item[3])
                elif kind == "control_state":
                    writer.control_state(item[1], item[2], item[3])
                elif kind == "event":
                    writer.event(*item[1:])
                written += 1
            writer.maybe_flush()
        except OSError as err:
            error = f"recording stopped: {path}: {err.strerror or err} after {written} messages"
            writer.abandon()
            conn.send(("alarm", error))
    result: dict[str, Any] = {
        "path": path,
        "messages": writer.messages,
        "error": error,
        "cpu_s": time.process_time() - cpu0,
    }
    if not error:
        try:
            writer.close()
            result["bytes"] = os.path.getsize(path)
        except OSError as err:
            result["error"] = f"recording stopped: {path}: {err.strerror or err} at its end"
            writer.abandon()
    conn.send(("result", result))


class Recorder:
    """Parent's handle on the recorder process.

    Parameters
    ----------
    path
        The ``.mcap`` file to write (made, or replaced).
    metadata
        Extra keys of the ``hapticloud`` metadata record (``source``, ``clock``, ...).
    config_toml
        ``perception``, ``fusion`` (and ``record``) parameters as TOML texts.
    scene
        ``{"name", "toml"}`` of the run's scene, or ``None``.
    record, crop
        What frames store (the crop's workspace decides the rectangle).
    limit_bytes
        A quota: writes past it fail as a full disk does (tests).
    """

    def __init__(
        self,
        path: str,
        metadata: Mapping[str, str],
        config_toml: Mapping[str, str],
        scene: Mapping[str, str] | None = None,
        record: RecordConfig | None = None,
        crop: CropConfig | None = None,
        limit_bytes: int | None = None,
    ) -> None:
        self.path = str(path)
        self.record = record or RecordConfig()
        ctx = mp.get_context("spawn")
        self._q = ctx.Queue(maxsize=self.record.queue_messages)
        self._conn, child = ctx.Pipe()
        toml = dict(config_toml)
        toml.setdefault("record", _toml(self.record))
        self._proc = ctx.Process(
            target=_recorder_entry,
            args=(
                self.path,
                self._q,
                child,
                {k: str(v) for k, v in metadata.items()},
                toml,
                None if scene is None else dict(scene),
                self.record,
                limit_bytes,
            ),
            name="hapticloud-recorder",
            daemon=True,
        )
        self.sink = RecordSink(self._q, self.record, crop or CropConfig())
        self.sink.alive = self._proc.is_alive
        self._alarms: list[str] = []
        self._result: dict[str, Any] | None = None
        self._proc.start()
        child.close()

    def wait_ready(self, timeout: float = 30.0) -> None:
        """Until the file is open (raises :class:`RecordingError` if it cannot be written)."""
        kind, payload = self._recv(timeout)
        if kind == "error":
            self._proc.join(5.0)
            raise RecordingError(payload)

    def _recv(self, timeout: float) -> tuple[str, Any]:
        try:
            if self._conn.poll(timeout):
                return self._conn.recv()
        except (EOFError, OSError):
            raise RecordingError(f"{self.path}: the recorder process ended") from None
        raise RecordingError(f"{self.path}: the recorder did not answer in {timeout:g} s")

    def alarms(self) -> list[str]:
        """Alarms since the last call (the recording stopped: disk full, ...)."""
        out = []
        while self._result is None and self._conn.poll(0):
            kind, payload = self._conn.recv()
            if kind == "alarm":
                self._alarms.append(payload)
                out.append(payload)
            elif kind == "result":
                self._result = payload
        return out

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def close(self, timeout: float = 60.0) -> dict[str, Any]:
        """Write what is queued, finish the file (indexed) and stop; the recorder's figures:
        ``messages``, ``bytes``, ``error`` (empty when complete), ``cpu_s``, ``dropped``."""
        self.alarms()
        if self._result is None:
            try:
                self._q.put(_STOP, timeout=timeout)
            except (queue.Full, ValueError, OSError):
                pass
            end = time.monotonic() + timeout
            while self._result is None and time.monotonic() < end:
                try:
                    kind, payload = self._recv(max(0.01, end - time.monotonic()))
                except (RecordingError, EOFError, OSError):
                    break
                if kind == "alarm":
                    self._alarms.append(payload)
                elif kind == "result":
                    self._result = payload
        self._proc.join(5.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(2.0)
        result = dict(self._result or {"path": self.path, "error": "the recorder did not finish"})
        result["dropped"] = self.sink.dropped
        result["alarms"] = list(self._alarms)
        return result


def _recorder_entry(*args: Any) -> None:
    try:
        _recorder_main(*args)
    except BaseException:
        try:
            args[2].send(("result", {"path": args[0], "error": traceback.format_exc()}))
        except Exception:
            pass


def _toml(config: Any) -> str:
    import tomli_w

    return tomli_w.dumps(config.to_dict())


def config_tomls(perception: Any, fusion: Any) -> dict[str, str]:
    """The ``hapticloud.config`` metadata of a run's parameters."""
    return {"perception": _toml(perception), "fusion": _toml(fusion)}


__all__ = [
    "RECORDER_NICE",
    "CutFrame",
    "FrameHeader",
    "RecordSink",
    "Recorder",
    "config_tomls",
    "cut_frame",
]
