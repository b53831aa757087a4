"""Recording a live session from the app: start and stop a recorder without blocking the window.

:class:`LiveRecording` owns one :class:`~.recorder.Recorder` (its process at ``nice`` +10, fed
by a queue that never blocks a producer). Starting it takes a process spawn and the file's
opening (~1 s) and finishing it writes the index, so both run on a helper thread: the window
asks, and reads :meth:`LiveRecording.status` on its timer (file, size, duration, messages,
dropped, the recorder's alarms).

What feeds it is the app's business: the perception worker cuts each frame it shows
(:func:`~.recorder.cut_frame`) into the display's own packet, the GUI process's receiver hands it
to :attr:`LiveRecording.sink`, and the session's drained control snapshots go to
:meth:`LiveRecording.control_snapshots`. The control loop records nothing.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hapticloud.core.errors import RecordingError
from hapticloud.core.recording import RecordConfig

from .recorder import Recorder, RecordSink, config_tomls


@dataclass(frozen=True)
class RecordingStatus:
    """What a Record button shows: ``state`` is ``starting``, ``recording``, ``finishing``,
    ``done`` or ``failed``; ``bytes`` the file's size now; ``duration_s`` since it started."""

    path: str
    state: str
    bytes: int
    duration_s: float
    messages: int
    dropped: int
    error: str = ""

    def line(self) -> str:
        name = Path(self.path).name
        size = self.bytes / 1e6
        text = f"{name}  {size:.1f} MB  {self.duration_s:.1f} s"
        if self.dropped:
            text += f"  ({self.dropped} dropped)"
        if self.state in ("starting", "finishing"):
            text += f"  {self.state}…"
        if self.error:
            text += f"  {self.error}"
        return text


class LiveRecording:
    """One recording of a live session (see the module docstring).

    Parameters
    ----------
    path
        The ``.mcap`` to write.
    perception, fusion
        The parameters the session runs with (the recording's ``hapticloud.config``).
    scene
        The scene's name (metadata) and, for a scene file, its TOML.
    record
        What frames store.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        perception: Any,
        fusion: Any,
        scene: str = "",
        scene_toml: Mapping[str, str] | None = None,
        record: RecordConfig | None = None,
        limit_bytes: int | None = None,
    ) -> None:
        self.path = str(path)
        self.record = record or RecordConfig()
        self._perception = perception
        self._fusion = fusion
        self._scene = scene
        self._scene_toml = None if scene_toml is None else dict(scene_toml)
        self._limit = limit_bytes
        self._recorder: Recorder | None = None
        self._state = "starting"
        self._error = ""
        self._result: dict[str, Any] | None = None
        self._started = time.monotonic()
        self._stopped_at: float | None = None
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._start, name="hapticloud-record", daemon=True)
        self._thread.start()

    # ----- life cycle -----------------------------------------------------------------------------
    def _start(self) -> None:
        try:
            recorder = Recorder(
                self.path,
                {"source": "app", "clock": "monotonic", "scene": self._scene},
                config_tomls(self._perception, self._fusion),
                self._scene_toml,
                record=self.record,
                crop=self._perception.crop,
                limit_bytes=self._limit,
            )
            recorder.wait_ready()
        except (RecordingError, OSError) as err:
            with self._lock:
                self._state, self._error = "failed", str(err).splitlines()[0]
            return
        with self._lock:
            self._recorder = recorder
            self._started = time.monotonic()
            stop = self._state == "finishing"  # stop() came while starting
            if not stop:
                self._state = "recording"
        if stop:
            self._finish()

    def stop(self) -> None:
        """Finish the file (index, close) on a helper thread; returns at once."""
        with self._lock:
            if self._state not in ("starting", "recording"):
                return
            starting = self._state == "starting"
            self._state = "finishing"
            self._stopped_at = time.monotonic()
        if not starting:
            threading.Thread(
                target=self._finish, name="hapticloud-record-stop", daemon=True
            ).start()

    def _finish(self) -> None:
        recorder = self._recorder
        result = recorder.close() if recorder is not None else {"error": "never started"}
        with self._lock:
            self._result = result
            self._error = str(result.get("error") or "")
            self._state = "failed" if self._error else "done"

    def wait(self, timeout_s: float = 30.0) -> bool:
        """Until started (or failed) and, after :meth:`stop`, finished; True if so in time."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self._state in ("recording", "done", "failed"):
                return True
            time.sleep(0.01)
        return False

    def wait_done(self, timeout_s: float = 60.0) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self._state in ("done", "failed"):
                return True
            time.sleep(0.01)
        return False

    # ----- feeding (any thread) -------------------------------------------------------------------
    @property
    def sink(self) -> RecordSink | None:
        """Where frames go (``None`` until started or once stopping)."""
        recorder = self._recorder
        return recorder.sink if recorder is not None and self._state == "recording" else None

    def put_cut(self, log_time_s: float, cut: Any) -> None:
        """A frame cut by the perception worker (:func:`~.recorder.cut_frame`); dropped while
        starting or stopping."""
        sink = self.sink
        if sink is not None:
            sink.put_cut(log_time_s, cut)

    def control_snapshots(self, snaps: list[Any], hip_radius_m: float) -> None:
        """Drained control snapshots as control states and events (monotonic clock)."""
        sink = self.sink
        if sink is None or not snaps:
            return
        from .runs import record_snapshots

        record_snapshots(sink, snaps, hip_radius_m)

    def event(self, level: str, source: str, text: str) -> None:
        """An event now (a parameter change, ...), on the monotonic clock."""
        sink = self.sink
        if sink is not None:
            sink.event(time.monotonic(), level, source, text)

    # ----- what the button shows ------------------------------------------------------------------
    @property
    def state(self) -> str:
        return self._state

    @property
    def result(self) -> dict[str, Any] | None:
        return self._result

    def status(self) -> RecordingStatus:
        recorder = self._recorder
        with self._lock:  # stop() hands the recorder's pipe to the finishing thread
            if recorder is not None and self._state == "recording":
                for alarm in recorder.alarms():
                    self._error = alarm
        try:
            size = os.path.getsize(self.path)
        except OSError:
            size = 0
        end = self._stopped_at if self._stopped_at is not None else time.monotonic()
        duration = 0.0 if self._state == "starting" else max(0.0, end - self._started)
        sink = recorder.sink if recorder is not None else None
        messages = int(self._result.get("messages", 0)) if self._result else 0
        return RecordingStatus(
            path=self.path,
            state=self._state,
            bytes=size,
            duration_s=duration,
            messages=messages or (sink.sent if sink is not None else 0),
            dropped=sink.dropped if sink is not None else 0,
            error=self._error,
        )


__all__ = ["LiveRecording", "RecordingStatus"]
