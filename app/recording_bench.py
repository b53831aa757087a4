"""The recording window's seek-to-screen time (``hapticloud bench seek FILE --gui``).

Opens :class:`~.recording_window.RecordingWindow` on the file, waits for the timeline, then for
each random time does what a click on the strip does (:meth:`TimelineWidget.seek`) and runs the
event loop until the 3D view has been painted with the snapshot at that time: the figure is
request to paint, the window's poll period (15 ms) included.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

from hapticloud.hardware.recording.seek_bench import latency_stats, seek_times
from PyQt6 import QtCore, QtWidgets

from .recording_source import RecordingSource
from .recording_window import RecordingWindow


class _PaintClock(QtCore.QObject):
    """Times of the 3D view's paints."""

    def __init__(self) -> None:
        super().__init__()
        self.last = 0.0

    def eventFilter(self, obj: QtCore.QObject, event: QtCore.QEvent) -> bool:  # noqa: N802
        if event.type() == QtCore.QEvent.Type.Paint:
            self.last = time.monotonic()
        return False


def _spin(app: QtWidgets.QApplication, until: Any, timeout_s: float = 30.0) -> None:
    end = time.monotonic() + timeout_s
    while not until():
        if time.monotonic() > end:
            raise TimeoutError("the window did not get there in time")
        app.processEvents(QtCore.QEventLoop.ProcessEventsFlag.AllEvents, 5)
        time.sleep(0.0005)


def gui_seek_bench(
    path: str | Path, seeks: int = 30, seed: int = 0, size: tuple[int, int] = (1440, 900)
) -> dict[str, Any]:
    """``{"size", "seek_ms": stats, "open_to_frame_ms"}`` for the window on ``path``."""
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(["hapticloud-bench"])
    t0 = time.monotonic()
    window = RecordingWindow(RecordingSource.open(path))
    clock = _PaintClock()
    window.view.canvas.installEventFilter(clock)
    window.resize(*size)
    window.show()
    try:
        _spin(app, lambda: window.shown is not None and clock.last > window.shown_at)
        open_to_frame = 1e3 * (clock.last - t0)
        player = window.source.player
        _spin(app, lambda: player.timeline.complete, 600.0)
        out = []
        for t in seek_times(player, seeks, seed):
            target = window.source.rel(t)
            started = time.monotonic()
            window.timeline.seek(t)

            def painted(target: float = target) -> bool:
                shown = window.shown
                return (
                    shown is not None
                    and math.isclose(shown.t, target, abs_tol=1e-9)
                    and clock.last > window.shown_at
                )

            _spin(app, painted)
            out.append(1e3 * (clock.last - started))
        return {
            "size": f"{size[0]}x{size[1]}",
            "open_to_frame_ms": open_to_frame,
            "seek_ms": latency_stats(out),
        }
    finally:
        window.close()
        window.shutdown()
        window.deleteLater()
        app.processEvents()


__all__ = ["gui_seek_bench"]
