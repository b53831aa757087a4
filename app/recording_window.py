"""The window on a recording: the live window's views, a timeline under the 3D view, re-runs.

``hapticloud app FILE.mcap`` opens this window. It is made of the live window's parts (the 3D
view with its tool bar and legend, the parameter panel, the plots, the status bar) fed by a
:class:`~.recording_source.RecordingSource` instead of a live source, with:

* the :class:`~.timeline.TimelineWidget` under the 3D view (transport, speed, steps, the
  click-to-jump strip with faults, holds, stops and contacts) and its keys
  (:func:`~.timeline.install_shortcuts`): no emergency stop here, nothing moves;
* the *Recording* dock: what the file is (source, scene, clock, duration, complete or not,
  channels), the re-run (perception and fusion with the panel's current parameters, on the whole
  recording, in a process: :class:`~hapticloud.hardware.recording.rerun.ReRun`; its estimates
  are drawn beside the recorded ones on the timeline and, at the cursor, in the 3D view in
  black) and the list of marks (a click jumps there).

:func:`open_recording_window` opens one from inside the app: a file that is not a readable
recording is a dialog, and the app goes on.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from hapticloud.core.errors import RecordingError
from hapticloud.hardware.live.contract import LiveConfig, Snapshot
from PyQt6 import QtCore, QtGui, QtWidgets

from .live_plots import LivePlots
from .main_window import PLOT_PERIOD_S, ViewControls, lay_out_docks
from .param_panel import ParamPanel
from .recording_source import RecordingSource
from .scene_view import SceneView
from .status import StatusPanel
from .timeline import MARK_COLOURS, TimelineWidget, install_shortcuts

#: How often the window polls its player (ms): up to ~60 Hz, so a seek shows within a poll;
#: a paint happens only when there is a new snapshot.
POLL_MS = 15

RERUN_MARKER_COLOUR = "#111111"
#: Marks listed in the dock (the strip shows them all).
MAX_LISTED_MARKS = 500


class RecordingPanel(QtWidgets.QWidget):
    """The *Recording* dock: file facts, the re-run and the marks (see the module docstring)."""

    def __init__(self, source: RecordingSource, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.source = source
        player = source.player
        rec = player.rec
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(6, 4, 6, 4)
        self.facts = QtWidgets.QLabel(self)
        self.facts.setWordWrap(True)
        self.facts.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        info = rec.info
        state = "complete" if rec.finished else f"UNFINISHED ({rec.truncation})"
        frames = sum(
            ch.messages for topic, ch in rec.channels.items() if topic.endswith("/capture")
        )
        note = f"<br><i>{player.layout.note}</i>" if player.layout.note else ""
        self.facts.setText(
            f"<b>{Path(rec.path).name}</b> — {state}<br>"
            f"{info.get('source', '?')} · scene {info.get('scene', '?')} · clock "
            f"{info.get('clock', '?')} · frames {info.get('frames', '?')}<br>"
            f"{rec.duration_s:.2f} s, {rec.message_count} messages, {frames} camera frames "
            f"({', '.join(rec.cameras) or 'no camera'}){note}"
        )
        layout.addWidget(self.facts)

        box = QtWidgets.QGroupBox("Re-run with the panel's parameters", self)
        rows = QtWidgets.QVBoxLayout(box)
        buttons = QtWidgets.QHBoxLayout()
        self.rerun_button = QtWidgets.QPushButton("Re-run", box)
        self.rerun_button.setToolTip(
            "re-run perception and fusion on every recorded frame with the Parameters panel's "
            "perception and fusion tables (each camera from its first frame); the new "
            "estimates are drawn in black beside the recorded ones"
        )
        self.cancel_button = QtWidgets.QPushButton("Cancel", box)
        self.cancel_button.setEnabled(False)
        buttons.addWidget(self.rerun_button)
        buttons.addWidget(self.cancel_button)
        rows.addLayout(buttons)
        self.progress = QtWidgets.QProgressBar(box)
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        self.progress.setTextVisible(True)
        rows.addWidget(self.progress)
        self.summary = QtWidgets.QLabel("not run", box)
        self.summary.setWordWrap(True)
        self.summary.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        box.setSizePolicy(
            QtWidgets.QSizePolicy.Policy.Preferred, QtWidgets.QSizePolicy.Policy.Minimum
        )
        rows.addWidget(self.summary)
        layout.addWidget(box)

        layout.addWidget(QtWidgets.QLabel("Marks (click to jump)", self))
        self.marks = QtWidgets.QListWidget(self)
        self.marks.setMinimumHeight(48)
        self.marks.itemActivated.connect(self._jump)
        self.marks.itemClicked.connect(self._jump)
        layout.addWidget(self.marks, 1)
        self._marks_id = -1
        self.cancel_button.clicked.connect(self.cancel_rerun)

    def _jump(self, item: QtWidgets.QListWidgetItem) -> None:
        t = item.data(QtCore.Qt.ItemDataRole.UserRole)
        if t is not None:
            self.source.player.seek(float(t))

    def cancel_rerun(self) -> None:
        rerun = self.source.player.rerun
        if rerun is not None:
            rerun.cancel()
        self.refresh()

    def refresh(self) -> None:
        player = self.source.player
        data = player.timeline
        if id(data) != self._marks_id:
            self._marks_id = id(data)
            self.marks.clear()
            for mark in data.marks[:MAX_LISTED_MARKS]:
                t0 = self.source.rel(mark.t0)
                span = mark.t1 - mark.t0
                text = f"{t0:8.3f} s  {mark.kind:8s} {mark.text}"
                if span > 0:
                    text += f" ({span:.2f} s)"
                item = QtWidgets.QListWidgetItem(text)
                item.setData(QtCore.Qt.ItemDataRole.UserRole, mark.t0)
                item.setForeground(QtGui.QBrush(QtGui.QColor(MARK_COLOURS[mark.kind])))
                self.marks.addItem(item)
        rerun = player.rerun
        if rerun is None:
            return
        total = max(rerun.total, 1)
        self.progress.setRange(0, total)
        self.progress.setValue(min(rerun.done, total))
        self.cancel_button.setEnabled(not rerun.finished)
        if rerun.error:
            self.summary.setText(f"<span style='color:#b00020'>re-run failed: {rerun.error}</span>")
        elif rerun.cancelled:
            self.summary.setText(f"cancelled after {rerun.done} frames")
        elif rerun.summary is not None:
            self.summary.setText(summary_text(rerun.summary))
        else:
            elapsed = time.monotonic() - rerun.started
            self.summary.setText(f"running: {rerun.done} of {rerun.total} frames, {elapsed:.0f} s")


def summary_text(s: dict) -> str:
    """The re-run's figures as the dock shows them."""

    def mm(key: str) -> str:
        v = s.get(key)
        return "\u2013" if v is None else f"{v:.3f} mm"

    compared = s.get("with_recorded_estimate", 0)
    return (
        f"{s.get('frames', 0)} frames, {s.get('identical', 0)} of {compared} identical to the "
        f"recording; valid only recorded {s.get('valid_recorded_only', 0)}, only re-run "
        f"{s.get('valid_new_only', 0)}; centroid max {mm('max_centroid_diff_mm')} "
        f"(median {mm('median_centroid_diff_mm')}), fused max {mm('max_fused_diff_mm')}; "
        f"ROI exceeded {s.get('roi_exceeded', 0)}; "
        f"{s.get('real_time_factor', math.nan):.1f}\u00d7 real time"
    )


class RecordingWindow(QtWidgets.QMainWindow):
    """A recording with its timeline (see the module docstring).

    Parameters
    ----------
    source
        An opened, not started :class:`RecordingSource` (started here).
    """

    def __init__(self, source: RecordingSource) -> None:
        super().__init__()
        self.source = source
        player = source.player
        self.setWindowTitle(f"hapticloud — {Path(player.path).name}")
        self.view = SceneView(self)
        self.controls = ViewControls(self.view, self)
        self.timeline = TimelineWidget(player, self)
        central = QtWidgets.QWidget(self)
        column = QtWidgets.QVBoxLayout(central)
        column.setContentsMargins(0, 0, 0, 0)
        column.setSpacing(0)
        column.addWidget(self.controls)
        column.addWidget(self.view, 1)
        column.addWidget(self.controls.legend)
        column.addWidget(self.timeline)
        self.setCentralWidget(central)

        self.panel = ParamPanel(source.requested_config, self)
        self.panel.config_changed.connect(self._apply_config)
        self.panel.refused.connect(lambda r: self.statusBar().showMessage(f"Refused: {r}", 8000))
        note = "A recording re-runs perception and fusion only."
        for top in ("haptics", "controller"):
            self.panel.set_table_note(top, note, read_only=True)
        for top in ("perception", "fusion"):
            self.panel.set_table_note(
                top,
                "Used by Re-run (Recording dock); the recorded values are loaded.",
                read_only=False,
            )
        self.plots = LivePlots(self)
        self.recording_panel = RecordingPanel(source, self)
        self.recording_panel.rerun_button.clicked.connect(self.start_rerun)
        lay_out_docks(
            self,
            (("Recording", self.recording_panel, 370), ("Parameters", self.panel, 360)),
            ("Plots", self.plots, 190),
        )
        self.status = StatusPanel(self.statusBar())
        self._build_toolbar()
        self.setMinimumSize(1024, 700)
        self.shortcuts = install_shortcuts(self, self.timeline, space=not _live_window_open())

        self._closed = False
        self._shown_seq = -1
        self._plotted = 0.0
        self.shown: Snapshot | None = None
        self.shown_at: float = math.nan
        self._pending: Snapshot | None = None
        self.children_windows: list[QtWidgets.QWidget] = []
        self.view.set_geometry(source.geometry)
        self.plots.set_geometry(source.geometry)
        # Without the simulator's bodies, the frames' own pixels show the surroundings.
        self.view.set_layer_visible("context", True, render=False)
        self.controls.layer_actions["context"].setChecked(True)
        self.controls.update_legend()
        source.start()
        self.timer = QtCore.QTimer(self)
        self.timer.setTimerType(QtCore.Qt.TimerType.PreciseTimer)
        self.timer.timeout.connect(self.poll)
        self.timer.start(POLL_MS)

    def _build_toolbar(self) -> None:
        bar = self.addToolBar("Recording")
        bar.setObjectName("Recording")
        bar.setMovable(False)
        opener = bar.addAction("Open recording…")
        opener.setShortcut(QtGui.QKeySequence("Ctrl+O"))
        opener.setToolTip("open another recording (.mcap) in a window of its own")
        opener.triggered.connect(lambda: ask_open_recording(self, self.children_windows))
        shot = bar.addAction("Screenshot…")
        shot.setToolTip("save the window as PNG")
        shot.triggered.connect(self._ask_screenshot)

    # ----- parameters and re-run ----------------------------------------------------------------
    def _apply_config(self, config: LiveConfig) -> None:
        self.source.request_config(config)

    def start_rerun(self) -> None:
        """Re-run the recording with the panel's perception and fusion (a process)."""
        config = self.panel.config
        assert isinstance(config, LiveConfig)
        self.source.player.start_rerun(config.perception, config.fusion)
        self.statusBar().showMessage("re-run started", 3000)
        self.recording_panel.refresh()

    # ----- display --------------------------------------------------------------------------------
    def poll(self) -> None:
        """Show the newest snapshot, move the timeline, take re-run rows (timer slot).

        The 3D view gets a new snapshot at once; the plots, the status bar and the dock follow
        at the next poll (at most every :data:`PLOT_PERIOD_S`): after a seek the view's paint
        comes first."""
        rerun = self.source.player.rerun
        if rerun is not None and not rerun.finished:
            rerun.poll()
        self.timeline.refresh()
        snap = self.source.latest()
        if snap is not None and snap.seq != self._shown_seq:
            self._shown_seq = snap.seq
            self.shown = snap
            self.shown_at = time.monotonic()
            self._show_rerun(snap)
            self.view.show_snapshot(snap)
            self._pending = snap
            return
        self.recording_panel.refresh()
        pending = self._pending
        now = time.monotonic()
        if pending is None or now - self._plotted < PLOT_PERIOD_S:
            return
        self._pending = None
        self._plotted = now
        self.plots.show_snapshot(pending)
        self.plots.show_control(self.source.control_history())
        self.status.show(pending, math.nan)
        player = self.source.player
        speed = self.status.labels.get("speed")
        if speed is not None:  # a recording has no simulation speed: say how it plays
            speed.setText(f"playing {player.speed:g}\u00d7" if player.playing else "paused")

    def _show_rerun(self, snap: Snapshot) -> None:
        """The re-run's estimates of each camera's newest frame at the cursor, in 3D."""
        rerun = self.source.player.rerun
        view = self.source.player.view
        if rerun is None or view is None or not len(rerun.rows.rows):
            self.view.show_markers("rerun", None)
            return
        centroids, normals = [], []
        rows = rerun.rows
        for cam in view.cameras:
            mine = rows.camera_rows(cam.name)
            if not len(mine) or not math.isfinite(cam.log_time_s):
                continue
            i = int(np.searchsorted(mine[:, 0], cam.log_time_s + 1e-9)) - 1
            if i < 0 or abs(mine[i, 0] - cam.log_time_s) > 1e-6 or mine[i, 2] != 1.0:
                continue
            centroids.append(mine[i, 3:6])
            normals.append(mine[i, 6:9])
        self.view.show_markers(
            "rerun",
            np.array(centroids) if centroids else None,
            np.array(normals) if normals else None,
            RERUN_MARKER_COLOUR,
        )

    # ----- screenshots and closing ----------------------------------------------------------------
    def _ask_screenshot(self) -> None:
        from .screenshot import save_window

        path, _ = QtWidgets.QFileDialog.getSaveFileName(
            self, "Save screenshot", "hapticloud.png", "PNG images (*.png)"
        )
        if path:
            save_window(self, Path(path))
            self.statusBar().showMessage(f"saved {path}", 5000)

    def shutdown(self) -> None:
        """Stop the timer, the player's threads and a re-run; release the view (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.timer.stop()
        self.source.close()
        self.view.close_view()
        for child in self.children_windows:
            child.close()

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:  # noqa: N802
        self.shutdown()
        super().closeEvent(event)


def _live_window_open() -> bool:
    """Whether a live window (whose emergency stop owns Space) is open in this app."""
    from .main_window import MainWindow

    app = QtWidgets.QApplication.instance()
    if app is None:
        return False
    return any(isinstance(w, MainWindow) and w.isVisible() for w in app.topLevelWidgets())


def open_recording_window(
    path: str | Path, parent: QtWidgets.QWidget | None = None
) -> RecordingWindow | None:
    """Open ``path`` in a new :class:`RecordingWindow`; a file that is not a readable recording
    is a warning dialog (``None`` returned) and nothing else changes."""
    try:
        source = RecordingSource.open(path)
    except RecordingError as err:
        box = QtWidgets.QMessageBox(
            QtWidgets.QMessageBox.Icon.Warning,
            "Cannot open the recording",
            str(err).splitlines()[0] if str(err) else "not a recording",
            QtWidgets.QMessageBox.StandardButton.Ok,
            parent,
        )
        box.setObjectName("recording-error")
        box.setAttribute(QtCore.Qt.WidgetAttribute.WA_DeleteOnClose)
        box.open()  # not modal to the app: the windows go on
        return None
    window = RecordingWindow(source)
    window.resize(1440, 900)
    window.show()
    return window


def ask_open_recording(
    parent: QtWidgets.QWidget, keep: list[QtWidgets.QWidget]
) -> RecordingWindow | None:
    """A file dialog for a ``.mcap``; opens it (:func:`open_recording_window`)."""
    path, _ = QtWidgets.QFileDialog.getOpenFileName(
        parent, "Open recording", "", "Recordings (*.mcap);;All files (*)"
    )
    if not path:
        return None
    window = open_recording_window(path, parent)
    if window is not None:
        keep.append(window)
    return window


__all__ = [
    "RecordingPanel",
    "RecordingWindow",
    "ask_open_recording",
    "open_recording_window",
    "summary_text",
]
