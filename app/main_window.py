"""The main window: assembles the 3D view, the parameter panel, the live plots and the status bar.

The window holds no state of its own beyond "which snapshot did I show last". A
:class:`QtCore.QTimer` at display rate pulls the newest snapshot from the source and hands it to
each view; a snapshot whose ``seq`` was already shown is dropped (the source may publish faster
or slower than the display). Parameter changes go to the source as built (validated) configs.

The emergency stop is an application-wide event filter, so Esc and Space stop the source whatever
widget has focus, dialogs included, before that widget sees the key. One exception keeps typing
possible: Space in a free-text field (a file name in a dialog) types a space; Esc always stops.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

from hapticloud.hardware.live.contract import (
    LiveConfig,
    SessionPhase,
    Snapshot,
    SnapshotSource,
    SourceState,
)
from hapticloud.hardware.live.session import Session
from PyQt6 import QtCore, QtGui, QtWidgets

from .live_plots import LivePlots
from .param_panel import ParamPanel
from .report import AppReport
from .scene_view import CAMERA_PRESETS, COLOR_MODES, LAYERS, SceneView
from .session_panel import STATE_STYLE, SessionPanel
from .status import StatusPanel

#: How often the live window polls its source (ms): at the cameras' 30 Hz; a paint happens only
#: when there is a new snapshot, and each shows both cameras' newest frames. Polled every 15 ms,
#: the off-screen canvas painted 33-36 frames/s, a new one for each camera's frame, which added
#: the window's CPU and showed nothing more.
LIVE_POLL_MS = 33
#: The plots are redrawn at most this often (s). At 10 Hz their painting and feeding took ~45 %
#: of the window's thread on the 2-core machine (py-spy, while the window was still composed
#: through OpenGL as a whole); at 5 Hz they still read as live, and the time saved goes to the
#: real-time perception worker (docs/benchmarks.md, "The worker in real time").
PLOT_PERIOD_S = 0.2
ESTOP_KEYS = (QtCore.Qt.Key.Key_Escape, QtCore.Qt.Key.Key_Space)

#: Builds a source for a configuration; with a session, called as ``make(config, session=attach)``
#: (the :class:`~hapticloud.hardware.live.worker.SessionAttach` or ``None``).
SourceFactory = Callable[..., SnapshotSource]
SessionFactory = Callable[[], Session]
#: Without a new perception frame, the view is still repainted this often (s) for the force arrow.
CONTROL_PAINT_S = 0.1


def _is_text_entry(obj: QtCore.QObject) -> bool:
    """True for a free-text field, where Space must type a space."""
    if isinstance(obj, QtWidgets.QTextEdit | QtWidgets.QPlainTextEdit):
        return True
    if not isinstance(obj, QtWidgets.QLineEdit):
        return False
    parent = obj.parent()
    numeric = isinstance(parent, QtWidgets.QAbstractSpinBox) or type(obj).__name__ == "SliderLabel"
    return not numeric


class EmergencyStopFilter(QtCore.QObject):
    """Application-wide: Esc (anywhere) and Space (anywhere but a text field) call ``trigger``.

    The key is swallowed, so it does not also toggle the focused check box or close a dialog.
    """

    def __init__(self, trigger: Callable[[str], None], parent: QtCore.QObject | None = None):
        super().__init__(parent)
        self._trigger = trigger

    def eventFilter(self, obj: QtCore.QObject, event: QtCore.QEvent) -> bool:  # noqa: N802
        kind = event.type()
        if kind not in (QtCore.QEvent.Type.KeyPress, QtCore.QEvent.Type.ShortcutOverride):
            return False
        assert isinstance(event, QtGui.QKeyEvent)
        if event.modifiers() & ~QtCore.Qt.KeyboardModifier.KeypadModifier:
            return False
        key = event.key()
        if key not in ESTOP_KEYS:
            return False
        if key == QtCore.Qt.Key.Key_Space and _is_text_entry(obj):
            return False
        if kind == QtCore.QEvent.Type.KeyPress and not event.isAutoRepeat():
            name = "Esc" if key == QtCore.Qt.Key.Key_Escape else "Space"
            self._trigger(f"emergency stop (key {name})")
        event.accept()
        return True


def add_dock(
    window: QtWidgets.QMainWindow,
    title: str,
    widget: QtWidgets.QWidget,
    area: QtCore.Qt.DockWidgetArea,
) -> None:
    """``widget`` in a movable, floatable (not closable) dock named ``title``."""
    dock = QtWidgets.QDockWidget(title, window)
    dock.setObjectName(title)
    dock.setWidget(widget)
    dock.setFeatures(
        QtWidgets.QDockWidget.DockWidgetFeature.DockWidgetMovable
        | QtWidgets.QDockWidget.DockWidgetFeature.DockWidgetFloatable
    )
    window.addDockWidget(area, dock)


def lay_out_docks(
    window: QtWidgets.QMainWindow,
    right: tuple[tuple[str, QtWidgets.QWidget, int], tuple[str, QtWidgets.QWidget, int]],
    bottom: tuple[str, QtWidgets.QWidget, int],
    right_width_px: int = 420,
) -> None:
    """The windows' dock layout: two panels stacked on the right (title, widget, height in px),
    ``right_width_px`` wide, and the plots along the bottom (title, widget, height)."""
    right_area = QtCore.Qt.DockWidgetArea.RightDockWidgetArea
    for title, widget, _ in right:
        add_dock(window, title, widget, right_area)
    add_dock(window, bottom[0], bottom[1], QtCore.Qt.DockWidgetArea.BottomDockWidgetArea)

    def dock(title: str) -> QtWidgets.QDockWidget:
        return window.findChild(QtWidgets.QDockWidget, title)

    vertical, horizontal = QtCore.Qt.Orientation.Vertical, QtCore.Qt.Orientation.Horizontal
    window.resizeDocks([dock(right[1][0])], [right_width_px], horizontal)
    window.resizeDocks([dock(title) for title, _, _ in right], [h for _, _, h in right], vertical)
    window.resizeDocks([dock(bottom[0])], [bottom[2]], vertical)


class ViewControls(QtWidgets.QToolBar):
    """Colour mode, layers, camera presets and the legend of the 3D view."""

    #: ``(layer key, shown)`` after the user shows or hides a layer.
    layer_changed = QtCore.pyqtSignal(str, bool)

    def __init__(self, view: SceneView, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__("View", parent)
        self.view = view
        self.setMovable(False)
        self.setIconSize(QtCore.QSize(16, 16))

        self.addWidget(QtWidgets.QLabel(" colour by ", self))
        self.color_mode = QtWidgets.QComboBox(self)
        self.color_mode.addItems(COLOR_MODES)
        self.color_mode.setCurrentText(view.color_mode)
        self.color_mode.setToolTip(
            "camera: each camera's points in its colour; stage: kept, "
            "filled from the ICP memory, cropped"
        )
        self.color_mode.currentTextChanged.connect(self._set_mode)
        self.addWidget(self.color_mode)

        layers = QtWidgets.QToolButton(self)
        layers.setText("layers")
        layers.setPopupMode(QtWidgets.QToolButton.ToolButtonPopupMode.InstantPopup)
        menu = QtWidgets.QMenu(layers)
        self.layer_actions: dict[str, QtGui.QAction] = {}
        for layer in LAYERS:
            action = menu.addAction(layer.label)
            action.setCheckable(True)
            action.setChecked(view.layer_visible(layer.key))
            action.toggled.connect(lambda on, key=layer.key: self._set_layer(key, on))
            self.layer_actions[layer.key] = action
        layers.setMenu(menu)
        self.addWidget(layers)
        self.addSeparator()

        self.addWidget(QtWidgets.QLabel(" camera ", self))
        group = QtGui.QActionGroup(self)
        self.preset_actions: dict[str, QtGui.QAction] = {}
        for preset, label in CAMERA_PRESETS.items():
            action = self.addAction(label)
            action.setCheckable(True)
            action.setChecked(preset == view.camera_preset)
            action.triggered.connect(lambda _=False, p=preset: view.set_camera_preset(p))
            group.addAction(action)
            self.preset_actions[preset] = action
        # The legend sits under the view (the window adds it): in the tool bar it would be the
        # first thing cut off at 1280 px.
        self.legend = QtWidgets.QLabel(parent)
        self.legend.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.legend.setContentsMargins(8, 2, 8, 2)
        self.update_legend()

    def _set_mode(self, mode: str) -> None:
        self.view.set_color_mode(mode)
        self.update_legend()

    def _set_layer(self, key: str, on: bool) -> None:
        self.view.set_layer_visible(key, on)
        self.update_legend()
        self.layer_changed.emit(key, on)

    def update_legend(self) -> None:
        items = self.view.legend()
        self.legend.setText(
            "&nbsp;".join(
                f"<span style='color:{colour}; font-size:14px'>●</span>&nbsp;{label}&nbsp;"
                for colour, label in items
            )
        )


class MainWindow(QtWidgets.QMainWindow):
    """The live view: 3D scene, parameters, plots, status, emergency stop.

    Parameters
    ----------
    make_source
        Builds a (not yet started) source for a configuration; called at start and on restart.
    config
        Initial parameters.
    title
        Shown in the title bar (the scene's name).
    make_session
        Builds the control process's :class:`Session` (started once, with the window; the
        perception worker is spawned attached to it). ``None``: perception only.
    """

    def __init__(
        self,
        make_source: SourceFactory,
        config: LiveConfig | None = None,
        title: str = "demo",
        *,
        make_session: SessionFactory | None = None,
    ) -> None:
        super().__init__()
        self.setWindowTitle(f"hapticloud — {title}")
        self._make_source = make_source
        config = LiveConfig() if config is None else config

        self.view = SceneView(self)
        self.controls = ViewControls(self.view, self)
        self.controls.layer_changed.connect(self._layer_changed)
        central = QtWidgets.QWidget(self)
        column = QtWidgets.QVBoxLayout(central)
        column.setContentsMargins(0, 0, 0, 0)
        column.setSpacing(0)
        column.addWidget(self.controls)
        column.addWidget(self.view, 1)
        column.addWidget(self.controls.legend)
        self.setCentralWidget(central)

        self.panel = ParamPanel(config, self)
        self.panel.config_changed.connect(self._apply_config)
        self.panel.refused.connect(self._show_refusal)
        self.plots = LivePlots(self)
        self.session_panel = SessionPanel(self)
        lay_out_docks(
            self,
            (("Session", self.session_panel, 250), ("Parameters", self.panel, 480)),
            ("Live plots", self.plots, 210),
        )

        self.status = StatusPanel(self.statusBar())
        self._build_toolbar()
        self.setMinimumSize(1024, 700)

        self._stop_filter = EmergencyStopFilter(self.emergency_stop, self)
        app = QtWidgets.QApplication.instance()
        assert app is not None
        app.installEventFilter(self._stop_filter)

        self._closed = False
        self._plotted = 0.0
        self._shown_seq = -1
        self.shown: Snapshot | None = None
        self._paints: deque[float] = deque(maxlen=61)
        self.view.canvas.installEventFilter(self)
        self.source: SnapshotSource | None = None
        self._make_session = make_session
        self.session: Session | None = None
        self._attached = False
        self._applied = config
        self._control_seq = -1
        #: Figures for ``hapticloud app --report`` (set by the command before the first poll).
        self.report: AppReport | None = None
        self._control_painted = 0.0
        self._control_plotted = 0.0
        if make_session is not None:
            self.session = make_session()
            self.session.start()  # returns at once; the source waits for it (poll)
        self.session_panel.set_session(self.session, self.emergency_stop)
        self._control_tables_note()
        self._start_source(config)
        self.timer = QtCore.QTimer(self)
        self.timer.setTimerType(QtCore.Qt.TimerType.PreciseTimer)
        self.timer.timeout.connect(self.poll)
        self.timer.start(LIVE_POLL_MS)

    # ----- layout -------------------------------------------------------------------------------
    def _build_toolbar(self) -> None:
        bar = self.addToolBar("Session")
        bar.setObjectName("Session")
        bar.setMovable(False)
        self.stop_button = QtWidgets.QPushButton("■  STOP  (Esc / Space)", self)
        self.stop_button.setToolTip("emergency stop: stops the live source at once")
        self.stop_button.setMinimumHeight(34)
        self.stop_button.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
        self.stop_button.setStyleSheet(
            "QPushButton { background:#c0392b; color:white; font-weight:700; font-size:14px;"
            " border-radius:4px; padding:4px 16px; }"
            "QPushButton:disabled { background:#7f8c8d; }"
        )
        self.stop_button.clicked.connect(lambda: self.emergency_stop("emergency stop (button)"))
        bar.addWidget(self.stop_button)
        self.restart_action = bar.addAction("Restart simulation")
        self.restart_action.setToolTip("start a new simulated session with the current parameters")
        self.restart_action.triggered.connect(self.restart)
        self.restart_action.setEnabled(False)
        bar.addSeparator()
        shot = bar.addAction("Screenshot…")
        shot.setToolTip("save the window as PNG")
        shot.triggered.connect(self._ask_screenshot)
        spacer = QtWidgets.QWidget(self)
        spacer.setSizePolicy(
            QtWidgets.QSizePolicy.Policy.Expanding, QtWidgets.QSizePolicy.Policy.Preferred
        )
        bar.addWidget(spacer)
        self.stop_label = QtWidgets.QLabel("", self)
        self.stop_label.setStyleSheet("color:#c0392b; font-weight:700; font-size:14px;")
        bar.addWidget(self.stop_label)

    # ----- the session -------------------------------------------------------------------------
    def _control_tables_note(self) -> None:
        """Say on the Haptics and Controller tabs whether a control process takes them."""
        session = self.session
        if session is None:
            note, read_only = "These act on the control process: no session runs.", True
        elif session.phase is SessionPhase.FAILED:
            note, read_only = f"No session ({session.message}): not applied.", True
        else:
            note, read_only = "Applied to the control loop at its next tick.", False
        self.panel.set_table_note("haptics", note, read_only=read_only)
        controller_note = note if read_only else f"{note} Only while the session is not enabled."
        self.panel.set_table_note("controller", controller_note, read_only=read_only)

    def _poll_session(self) -> None:
        session = self.session
        if session is None:
            return
        snap = session.poll()
        state = self.session_panel.state_text()
        if self.report is not None:
            self.report.observe_session(state, session)
        self.session_panel.refresh()
        self.status.show_session(
            state, session.latest, STATE_STYLE.get(state, STATE_STYLE["closed"])
        )
        if snap is None or snap.seq == self._control_seq:
            return
        self._control_seq = snap.seq
        self.view.show_control(snap)
        now = time.monotonic()
        if now - self._control_plotted >= PLOT_PERIOD_S:
            self._control_plotted = now
            self.plots.show_control(session.history())

    # ----- the source -------------------------------------------------------------------------
    def _start_source(self, config: LiveConfig) -> None:
        session = self.session
        if session is not None:
            # A session still starting is attached by poll() once it runs.
            source = self._make_source(config, session=session.attach)
            self._attached = session.running
        else:
            source = self._make_source(config)
        self.view.set_geometry(source.geometry)
        self.plots.set_geometry(source.geometry)
        self.controls.update_legend()
        self._shown_seq = -1
        self.shown = None
        self.source = source
        self._want_context()
        source.start()
        self.stop_button.setEnabled(True)
        self.stop_label.setText("")
        self.status.set_state(SourceState.STARTING, "")

    def _layer_changed(self, key: str, on: bool) -> None:
        if key == "context":
            self._want_context()

    def _want_context(self) -> None:
        """The worker renders the scene clouds only while their layer is shown (they cost it
        ~4 % of a core at 5 Hz a camera, for a picture nobody sees otherwise)."""
        want = getattr(self.source, "want_context", None)
        if want is not None:
            want(self.view.layer_visible("context"))

    def restart(self) -> None:
        """Replace a stopped source by a new one with the current parameters."""
        if self.source is not None:
            self.source.close()
        self.restart_action.setEnabled(False)
        self._start_source(self.panel.config)  # type: ignore[arg-type]

    def emergency_stop(self, reason: str = "emergency stop") -> None:
        """Stop the source now and show STOPPED (the source confirms with its next snapshot)."""
        if self.session is not None:
            self.session.emergency_stop(reason)  # the drives first
        if self.source is not None:
            self.source.emergency_stop(reason)
        self.stop_label.setText(f"STOPPED — {reason}")
        self.stop_button.setEnabled(False)
        self.restart_action.setEnabled(True)
        self.view.show_stopped()
        self.status.set_state(SourceState.STOPPED, reason)
        self.statusBar().showMessage(f"STOPPED: {reason}", 0)

    @property
    def stopped(self) -> bool:
        return not self.stop_button.isEnabled()

    def _apply_config(self, config: LiveConfig) -> None:
        if self.source is not None:
            self.source.request_config(config)
        session, old = self.session, self._applied
        self._applied = config
        if session is None or not session.running:
            return
        haptics = config.haptics if config.haptics != old.haptics else None
        fusion = config.fusion if config.fusion != old.fusion else None
        controller = config.controller if config.controller != old.controller else None
        changed = haptics is not None or fusion is not None or controller is not None
        if changed:
            session.configure(haptics=haptics, fusion=fusion, controller=controller)

    def _show_refusal(self, reason: str) -> None:
        self.statusBar().showMessage(f"Refused: {reason}", 8000)

    # ----- display ------------------------------------------------------------------------------
    def poll(self) -> None:
        """Show the newest snapshot if it is newer than the one shown (timer slot)."""
        self._poll_session()
        session, source = self.session, self.source
        started = session is not None and session.phase is not SessionPhase.STARTING
        if session is not None and started and not self._attached:
            self._attached = True
            self._control_tables_note()
            attach = session.attach
            if attach is None:
                self.statusBar().showMessage(f"{session.message}; perception only", 0)
            elif source is not None and hasattr(source, "attach_session"):
                source.attach_session(attach)
        if source is None:
            return
        snap = source.latest()
        if snap is None or snap.seq <= self._shown_seq:
            # No new frame (stopped, or between frames): the force arrow still moves.
            now = time.monotonic()
            if self.session is not None and now - self._control_painted >= CONTROL_PAINT_S:
                self._control_painted = now
                self.view.request_render()
            return
        self._control_painted = time.monotonic()
        self._shown_seq = snap.seq
        self.shown = snap
        self.view.show_snapshot(snap)
        now = time.monotonic()
        if self.report is not None:
            self.report.observe_frame(snap, self.view_fps, now)
        if now - self._plotted >= PLOT_PERIOD_S or snap.state is not SourceState.RUNNING:
            self._plotted = now
            self.plots.show_snapshot(snap)
        # Snapshots published before a requested stop still say RUNNING: the stop wins.
        stopping = self.stopped and snap.state is SourceState.RUNNING
        self.status.show(snap, self.view_fps, state=SourceState.STOPPED if stopping else None)
        if snap.state in (SourceState.STOPPED, SourceState.FAILED) and not self.stopped:
            # Stopped or failed by itself (not by the button): same display as an e-stop.
            self.emergency_stop(snap.message or snap.state.value)

    @property
    def view_fps(self) -> float:
        """Paints of the 3D view per second, over the last ~60 paints."""
        if len(self._paints) < 3:
            return math.nan
        span = self._paints[-1] - self._paints[0]
        return (len(self._paints) - 1) / span if span > 0 else math.nan

    def eventFilter(self, obj: QtCore.QObject, event: QtCore.QEvent) -> bool:  # noqa: N802
        if obj is self.view.canvas and event.type() == QtCore.QEvent.Type.Paint:
            self._paints.append(time.monotonic())
        return False

    # ----- screenshots and closing ------------------------------------------------------------
    def _ask_screenshot(self) -> None:
        from .screenshot import save_window

        path, _ = QtWidgets.QFileDialog.getSaveFileName(
            self, "Save screenshot", "hapticloud.png", "PNG images (*.png)"
        )
        if path:
            save_window(self, Path(path))
            self.statusBar().showMessage(f"saved {path}", 5000)

    def shutdown(self) -> None:
        """Stop the timer and the source, release the render window (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.timer.stop()
        app = QtWidgets.QApplication.instance()
        if app is not None:
            app.removeEventFilter(self._stop_filter)
        if self.source is not None:
            self.source.close()
        if self.session is not None:
            self.session.close()
        self.view.close_view()

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:  # noqa: N802
        self.shutdown()
        super().closeEvent(event)
