"""The live window's Record button: record the session shown to an MCAP file, live.

:func:`install_record_controls` puts a *Record* button, the recording's file name, size and
duration (refreshed 4 times a second) and an *Open recording…* action into a
:class:`~.main_window.MainWindow`'s session tool bar. Recording uses
:class:`~hapticloud.hardware.recording.live.LiveRecording` (the recorder process at ``nice``
+10, started and finished on a helper thread) fed by what the display gets:

* every frame the window's perception worker shows, cut to the stored rectangle in the worker
  and carried by the display's own packet
  (:meth:`~hapticloud.hardware.live.source.LiveSource.record_to`);
* the control snapshots the session drains for the session panel
  (:attr:`~.session.Session.listeners`), as control states and events;
* each parameter change, as an event.

The control loop records nothing. A restarted perception worker is fed to the same recording.
Closing the window finishes the file.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from hapticloud.core.config import StageConfig
from hapticloud.hardware.recording.live import LiveRecording
from PyQt6 import QtCore, QtWidgets

REFRESH_MS = 250
IDLE_STYLE = "QPushButton { font-weight:600; padding:4px 10px; }"
RECORDING_STYLE = (
    "QPushButton { background:#b00020; color:white; font-weight:700; padding:4px 10px;"
    " border-radius:4px; }"
)


def default_path(folder: str | Path = ".") -> Path:
    """``hapticloud-YYYYmmdd-HHMMSS.mcap`` in ``folder``."""
    return Path(folder) / time.strftime("hapticloud-%Y%m%d-%H%M%S.mcap")


def _flat(config: StageConfig) -> dict[str, Any]:
    out: dict[str, Any] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else k, v)
        else:
            out[prefix] = value

    walk("", config.to_dict())
    return out


class RecordControls(QtWidgets.QWidget):
    """Record button and live label for ``window`` (see the module docstring)."""

    def __init__(self, window: Any, folder: str | Path = ".") -> None:
        super().__init__(window)
        self.window_ = window
        self.folder = Path(folder)
        self.recording: LiveRecording | None = None
        self.finished: list[LiveRecording] = []
        self._source: Any = None
        self._config = window.panel.config
        row = QtWidgets.QHBoxLayout(self)
        row.setContentsMargins(6, 0, 6, 0)
        self.button = QtWidgets.QPushButton("●  Record", self)
        self.button.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
        self.button.setToolTip(
            "record what the window shows (camera frames, estimates, the session's control "
            "states and events) to an MCAP file; 'hapticloud app FILE.mcap' opens it"
        )
        self.button.setStyleSheet(IDLE_STYLE)
        self.button.clicked.connect(self.toggle)
        self.label = QtWidgets.QLabel("", self)
        self.label.setMinimumWidth(260)
        row.addWidget(self.button)
        row.addWidget(self.label)
        window.panel.config_changed.connect(self._config_changed)
        session = getattr(window, "session", None)
        if session is not None and hasattr(session, "listeners"):
            session.listeners.append(self._snapshots)
        self.timer = QtCore.QTimer(self)
        self.timer.timeout.connect(self.refresh)
        self.timer.start(REFRESH_MS)
        window.installEventFilter(self)

    def eventFilter(self, obj: QtCore.QObject, event: QtCore.QEvent) -> bool:  # noqa: N802
        """The window closes: finish the file before the window stops its sources."""
        if obj is self.window_ and event.type() == QtCore.QEvent.Type.Close:
            self.finish()
        return False

    # ----- actions --------------------------------------------------------------------------------
    def toggle(self) -> None:
        if self.recording is not None and self.recording.state in ("starting", "recording"):
            self.stop()
        else:
            self.start()

    def start(self, path: str | Path | None = None) -> LiveRecording:
        """Start recording to ``path`` (default: :func:`default_path` in the folder)."""
        self.stop()
        window = self.window_
        config = window.panel.config
        source = window.source
        scene = getattr(getattr(source, "settings", None), "scene", "") or ""
        self.recording = LiveRecording(
            path or default_path(self.folder), config.perception, config.fusion, scene=scene
        )
        self._config = config
        self._source = None
        self.refresh()
        return self.recording

    def stop(self) -> None:
        """Stop recording; the file is finished on a helper thread."""
        rec = self.recording
        if rec is None:
            return
        source = self._source
        if source is not None and hasattr(source, "record_to"):
            try:
                source.record_to(None)
            except (ValueError, OSError):
                pass  # the source is closed already: it sends nothing more
        self._source = None
        rec.stop()
        self.finished.append(rec)
        self.refresh()

    def finish(self, timeout_s: float = 30.0) -> None:
        """Stop and wait until every file is finished (the app is quitting)."""
        self.stop()
        for rec in self.finished:
            rec.wait_done(timeout_s)

    # ----- feeding --------------------------------------------------------------------------------
    def _snapshots(self, snaps: list[Any]) -> None:
        rec = self.recording
        if rec is not None and rec.state == "recording":
            source = self.window_.source
            r_hip = source.geometry.r_hip_m if source is not None else 0.04
            rec.control_snapshots(snaps, r_hip)

    def _config_changed(self, config: Any) -> None:
        rec, old = self.recording, self._config
        self._config = config
        if rec is None or rec.state != "recording" or old is None:
            return
        before, after = _flat(old), _flat(config)
        changed = [
            f"{k} {before.get(k)!r} -> {v!r}" for k, v in after.items() if before.get(k) != v
        ]
        if changed:
            rec.event("info", "config", "parameters changed: " + "; ".join(changed))

    # ----- display --------------------------------------------------------------------------------
    def refresh(self) -> None:
        rec = self.recording
        window = self.window_
        if rec is not None and rec.state == "recording":
            source = window.source
            if source is not self._source and hasattr(source, "record_to"):
                source.record_to(rec)  # the first frames, or a restarted worker
                self._source = source
        active = rec is not None and rec.state in ("starting", "recording")
        text = "■  Stop recording" if active else "●  Record"
        if self.button.text() != text:
            self.button.setText(text)
            self.button.setStyleSheet(RECORDING_STYLE if active else IDLE_STYLE)
        if rec is None:
            self.label.setText("")
            return
        status = rec.status()
        prefix = "REC " if active else ""
        self.label.setText(prefix + status.line())
        self.label.setToolTip(status.path)
        colour = "#b00020" if active or status.error else "#333333"
        self.label.setStyleSheet(f"color:{colour};")


def install_record_controls(
    window: Any, record: str | Path | None = None, folder: str | Path = "."
) -> RecordControls:
    """Add the Record button (and *Open recording…*) to ``window``'s session tool bar; with
    ``record``, start recording there at once. The recording is finished when the app quits."""
    bar = window.findChild(QtWidgets.QToolBar, "Session")
    controls = RecordControls(window, folder)
    if bar is not None:
        bar.addSeparator()
        bar.addWidget(controls)
        from .recording_window import ask_open_recording

        keep: list[QtWidgets.QWidget] = []
        controls.opened = keep  # type: ignore[attr-defined]
        action = bar.addAction("Open recording…")
        action.setToolTip("open a recording (.mcap) in a window of its own; the session goes on")
        action.triggered.connect(lambda: ask_open_recording(window, keep))
    app = QtWidgets.QApplication.instance()
    if app is not None:
        app.aboutToQuit.connect(controls.finish)
    window.record_controls = controls
    if record is not None:
        controls.start(record)
    return controls


__all__ = ["RecordControls", "default_path", "install_record_controls"]
