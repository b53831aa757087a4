"""The recording's timeline under the 3D view: transport buttons and a click-to-jump strip.

:class:`TimelineWidget` drives a :class:`~hapticloud.hardware.recording.cursor.RecordingPlayer`
(play/pause, speed, steps of +-100 ms and +-1 s, start/end) and draws :class:`TimelineStrip`:

* a marks lane: faults (red), holds (amber), stops (brown) and contacts (blue) from
  :func:`~hapticloud.hardware.recording.timeline.timeline_marks`;
* one lane per camera: where its recorded estimate was valid (its colour) or not (grey); with a
  re-run, a second lane under it for the re-run's estimates;
* ``d_proj`` (mm) of each camera's recorded estimates (its colour) and of the re-run's (black),
  per pixel column its range, on the same time axis;
* the part of the file the scan has not read yet (hatched) and the cursor (red line).

A click or drag on the strip seeks; the tool tip names the marks under the mouse. The strip is
drawn into a cached image when its data or size change; a cursor move repaints only the line
over it. The keyboard shortcuts are the window's (:func:`install_shortcuts`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from hapticloud.hardware.recording.cursor import SPEEDS, RecordingPlayer
from hapticloud.hardware.recording.timeline import MARK_KINDS, TimelineData, merge_marks
from numpy.typing import NDArray
from PyQt6 import QtCore, QtGui, QtWidgets

from .scene_view import CAMERA_COLOURS

MARK_COLOURS = {
    "fault": "#c0392b",
    "hold": "#f0ad00",
    "stop": "#8c510a",
    "contact": "#1f78b4",
}
MARK_LABELS = {"fault": "fault", "hold": "hold", "stop": "stop", "contact": "contact"}
INVALID_COLOUR = "#d0d0d0"
UNREAD_COLOUR = "#eeeeee"
CURSOR_COLOUR = "#e41a1c"
RERUN_COLOUR = "#111111"
#: Steps of the step buttons and arrow keys (s).
SMALL_STEP_S = 0.1
LARGE_STEP_S = 1.0
#: d_proj axis of the strip (mm): at least this range, grown to the recorded values' 1st and 99th
#: percentiles (at most D_PROJ_MAX_MM: farther is clipped at the top).
D_PROJ_RANGE_MM = (-5.0, 40.0)
D_PROJ_MAX_MM = 400.0
#: A lane holds an estimate's state this long (s) until the next one.
HOLD_S = 0.5
MARKS_H = 14
LANE_H = 7
PLOT_H = 34
GAP = 3
LEFT = 64  # the lanes' names


def _fmt_time(t: float) -> str:
    if not math.isfinite(t):
        return "\u2013"
    minutes, seconds = divmod(max(t, 0.0), 60.0)
    return f"{int(minutes)}:{seconds:06.3f}" if minutes else f"{seconds:.3f} s"


class TimelineStrip(QtWidgets.QWidget):
    """The click-to-jump strip (see the module docstring)."""

    seek_requested = QtCore.pyqtSignal(float)

    def __init__(self, start_s: float, end_s: float, parent: QtWidgets.QWidget | None = None):
        super().__init__(parent)
        self.start_s, self.end_s = start_s, end_s
        self.cursor_s = start_s
        self.data: TimelineData | None = None
        self.rerun: object | None = None
        self._rerun_version = 0
        self.cameras: tuple[str, ...] = ()
        self.r_hip_m = 0.04
        self._image: QtGui.QImage | None = None
        self._image_key: tuple | None = None
        self._d_range_now = D_PROJ_RANGE_MM
        self.repaints = 0
        self.setMouseTracking(True)
        self.setSizePolicy(
            QtWidgets.QSizePolicy.Policy.Expanding, QtWidgets.QSizePolicy.Policy.Fixed
        )
        self.setMinimumWidth(320)
        self.setCursor(QtCore.Qt.CursorShape.PointingHandCursor)
        self.setToolTip("click or drag to jump; the marks are named here")

    # ----- geometry -------------------------------------------------------------------------------
    @property
    def duration_s(self) -> float:
        return max(self.end_s - self.start_s, 1e-9)

    def lane_count(self) -> int:
        rerun = 2 if self.rerun is not None else 1
        return len(self.cameras) * rerun

    def sizeHint(self) -> QtCore.QSize:  # noqa: N802
        return QtCore.QSize(800, self._height())

    def _height(self) -> int:
        return MARKS_H + GAP + self.lane_count() * (LANE_H + 1) + GAP + PLOT_H + 4

    def x_of(self, t: float) -> float:
        w = max(self.width() - LEFT - 4, 1)
        return LEFT + (t - self.start_s) / self.duration_s * w

    def t_of(self, x: float) -> float:
        w = max(self.width() - LEFT - 4, 1)
        return self.start_s + min(max((x - LEFT) / w, 0.0), 1.0) * self.duration_s

    # ----- data -----------------------------------------------------------------------------------
    def set_data(self, data: TimelineData, cameras: tuple[str, ...], r_hip_m: float) -> None:
        grow = len(cameras) != len(self.cameras)
        self.data, self.cameras, self.r_hip_m = data, cameras, r_hip_m
        if grow:
            self.setFixedHeight(self._height())
        self.update()

    def set_rerun(self, rerun: object | None) -> None:
        """Draw ``rerun``'s rows (again: call it when more arrived)."""
        had = self.rerun is not None
        self.rerun = rerun
        self._rerun_version += 1
        if had != (rerun is not None):
            self.setFixedHeight(self._height())
        self.update()

    def set_cursor(self, t: float) -> None:
        if t != self.cursor_s:
            old = self.x_of(self.cursor_s)
            self.cursor_s = t
            new = self.x_of(t)
            lo, hi = min(old, new), max(old, new)
            self.update(QtCore.QRect(int(lo) - 3, 0, int(hi - lo) + 7, self.height()))

    # ----- painting -------------------------------------------------------------------------------
    def _key(self) -> tuple:
        return (self.width(), self.height(), id(self.data), self._rerun_version)

    def paintEvent(self, event: QtGui.QPaintEvent) -> None:  # noqa: N802
        key = self._key()
        if self._image is None or key != self._image_key:
            self._image = self._render()
            self._image_key = key
        painter = QtGui.QPainter(self)
        painter.drawImage(0, 0, self._image)
        x = self.x_of(self.cursor_s)
        painter.setPen(QtGui.QPen(QtGui.QColor(CURSOR_COLOUR), 2))
        painter.drawLine(QtCore.QPointF(x, 0), QtCore.QPointF(x, self.height()))
        painter.end()
        self.repaints += 1

    def _columns(self, t: NDArray[np.float64]) -> NDArray[np.int64]:
        w = max(self.width() - LEFT - 4, 1)
        cols = ((t - self.start_s) / self.duration_s * w).astype(np.int64)
        return np.clip(cols, 0, w - 1)

    def _render(self) -> QtGui.QImage:
        ratio = self.devicePixelRatioF() or 1.0
        image = QtGui.QImage(
            max(1, round(self.width() * ratio)),
            max(1, round(self.height() * ratio)),
            QtGui.QImage.Format.Format_ARGB32_Premultiplied,
        )
        image.setDevicePixelRatio(ratio)
        image.fill(QtGui.QColor("#fbfbfb"))
        p = QtGui.QPainter(image)
        font = p.font()
        font.setPointSizeF(7.5)
        p.setFont(font)
        w = max(self.width() - LEFT - 4, 1)
        data = self.data
        y = 0
        # lane names
        p.setPen(QtGui.QColor("#555555"))
        p.drawText(QtCore.QRectF(2, y, LEFT - 4, MARKS_H), _right_mid(), "marks")
        lanes_y = MARKS_H + GAP
        names: list[tuple[str, str]] = []
        for name in self.cameras:
            names.append((name, name))
            if self.rerun is not None:
                names.append((name, "re-run"))
        for i, (_cam, label) in enumerate(names):
            p.drawText(
                QtCore.QRectF(2, lanes_y + i * (LANE_H + 1) - 2, LEFT - 4, LANE_H + 4),
                _right_mid(),
                label,
            )
        plot_y = lanes_y + len(names) * (LANE_H + 1) + GAP
        self._d_range_now = self._d_range()
        hi = self._d_range_now[1]
        p.drawText(
            QtCore.QRectF(2, plot_y, LEFT - 4, PLOT_H),
            _right_mid(),
            f"d_proj\n{hi:.0f} mm" if hi != D_PROJ_RANGE_MM[1] else "d_proj",
        )
        p.fillRect(QtCore.QRectF(LEFT, plot_y, w, PLOT_H), QtGui.QColor("#ffffff"))
        # zero line of d_proj
        y0 = self._plot_y(0.0, plot_y)
        p.setPen(QtGui.QPen(QtGui.QColor("#bbbbbb"), 1, QtCore.Qt.PenStyle.DashLine))
        p.drawLine(QtCore.QPointF(LEFT, y0), QtCore.QPointF(LEFT + w, y0))
        if data is not None:
            self._paint_marks(p, data, w)
            for i, name in enumerate(self.cameras):
                row = i * (2 if self.rerun is not None else 1)
                lane = data.camera(name)
                colour = CAMERA_COLOURS[i % len(CAMERA_COLOURS)]
                if lane is not None and len(lane.t):
                    self._paint_validity(
                        p, lane.t, lane.valid, lanes_y + row * (LANE_H + 1), colour
                    )
                    self._paint_range(p, lane.t, lane.d_proj_mm, plot_y, colour)
            # what the scan has not read yet
            if not data.complete:
                x0 = LEFT + (data.scanned_s - self.start_s) / self.duration_s * w
                brush = QtGui.QBrush(QtGui.QColor("#c8c8c8"), QtCore.Qt.BrushStyle.BDiagPattern)
                p.fillRect(QtCore.QRectF(x0, 0, LEFT + w - x0, self.height()), brush)
        rerun = self.rerun
        if rerun is not None:
            rows = getattr(rerun, "rows", None)
            if rows is not None and len(rows.rows):
                for i, name in enumerate(self.cameras):
                    mine = rows.camera_rows(name)
                    if not len(mine):
                        continue
                    colour = CAMERA_COLOURS[i % len(CAMERA_COLOURS)]
                    t = mine[:, 0]
                    valid = mine[:, 2] == 1.0
                    yy = lanes_y + (2 * i + 1) * (LANE_H + 1)
                    self._paint_validity(p, t, valid, yy, colour)
                    dp = rows.d_proj_mm(mine, self.r_hip_m, "new")
                    self._paint_range(p, t, dp, plot_y, RERUN_COLOUR, width=1)
                done_t = float(rows.rows[-1, 0])
                if not getattr(rerun, "finished", True):
                    x0 = LEFT + (done_t - self.start_s) / self.duration_s * w
                    p.fillRect(
                        QtCore.QRectF(x0, lanes_y, LEFT + w - x0, plot_y - lanes_y),
                        QtGui.QColor(255, 255, 255, 150),
                    )
        p.setPen(QtGui.QColor("#999999"))
        p.drawRect(QtCore.QRectF(LEFT, 0, w, self.height() - 1))
        p.end()
        return image

    def _d_range(self) -> tuple[float, float]:
        """The strip's d_proj axis for the data (see :data:`D_PROJ_RANGE_MM`)."""
        lo, hi = D_PROJ_RANGE_MM
        data = self.data
        if data is not None:
            parts = [lane.d_proj_mm[np.isfinite(lane.d_proj_mm)] for lane in data.cameras]
            values = np.concatenate(parts) if parts else np.empty(0)
            if len(values):
                p1, p99 = np.percentile(values, (1.0, 99.0))
                lo, hi = min(lo, float(p1)), min(max(hi, float(p99)), D_PROJ_MAX_MM)
        return lo, hi

    def _plot_y(self, d_mm: float | NDArray, plot_y: float) -> float | NDArray:
        lo, hi = self._d_range_now
        frac = (np.clip(d_mm, lo, hi) - lo) / (hi - lo)
        return plot_y + PLOT_H - 2 - frac * (PLOT_H - 4)

    def _paint_marks(self, p: QtGui.QPainter, data: TimelineData, w: int) -> None:
        min_gap = 2.0 * self.duration_s / w  # two pixels
        rows = {kind: k for k, kind in enumerate(MARK_KINDS)}
        h = MARKS_H / len(MARK_KINDS)
        for mark in merge_marks(data.marks, min_gap):
            x0 = self.x_of(mark.t0)
            x1 = max(self.x_of(mark.t1), x0 + 2.0)
            yy = rows.get(mark.kind, 0) * h
            p.fillRect(QtCore.QRectF(x0, yy, x1 - x0, h), QtGui.QColor(MARK_COLOURS[mark.kind]))

    def _paint_validity(
        self, p: QtGui.QPainter, t: NDArray, valid: NDArray[np.bool_], y: float, colour: str
    ) -> None:
        """Per pixel column: valid if most estimates in it were; a column without one holds the
        state of the newest before it (for at most :data:`HOLD_S`: a camera that stopped shows
        nothing)."""
        w = max(self.width() - LEFT - 4, 1)
        if not len(t):
            return
        cols = self._columns(t)
        total = np.bincount(cols, minlength=w)[:w]
        good = np.bincount(cols, weights=valid.astype(np.float64), minlength=w)[:w]
        have = total > 0
        state = np.full(w, -1, dtype=np.int8)
        state[have] = (good[have] / total[have] >= 0.5).astype(np.int8)
        # hold: each empty column takes the last filled column's state, within HOLD_S
        idx = np.where(have, np.arange(w), -1)
        last = np.maximum.accumulate(idx)
        hold_cols = HOLD_S / self.duration_s * w
        fill = (~have) & (last >= 0) & (np.arange(w) - last <= hold_cols)
        state[fill] = state[last[fill]]
        ok, bad = QtGui.QColor(colour), QtGui.QColor(INVALID_COLOUR)
        breaks = np.flatnonzero(np.diff(state) != 0) + 1
        for run in np.split(np.arange(w), breaks):
            s0 = state[run[0]]
            if s0 < 0:
                continue
            c0, c1 = run[0], run[-1]
            p.fillRect(QtCore.QRectF(LEFT + c0, y, c1 - c0 + 1, LANE_H), ok if s0 else bad)

    def _paint_range(
        self,
        p: QtGui.QPainter,
        t: NDArray,
        values: NDArray,
        plot_y: float,
        colour: str,
        width: float = 1.0,
    ) -> None:
        keep = np.isfinite(values)
        if not keep.any():
            return
        w = max(self.width() - LEFT - 4, 1)
        cols = self._columns(t[keep])
        v = values[keep]
        lo = np.full(w, np.inf)
        hi = np.full(w, -np.inf)
        np.minimum.at(lo, cols, v)
        np.maximum.at(hi, cols, v)
        have = np.flatnonzero(np.isfinite(lo))
        y_lo = self._plot_y(lo[have], plot_y)
        y_hi = self._plot_y(hi[have], plot_y)
        p.setPen(QtGui.QPen(QtGui.QColor(colour), width))
        lines = [
            QtCore.QLineF(LEFT + c + 0.5, a + 0.5, LEFT + c + 0.5, b - 0.5)
            for c, a, b in zip(have, y_lo, y_hi, strict=True)
        ]
        p.drawLines(lines)

    # ----- mouse ----------------------------------------------------------------------------------
    def mousePressEvent(self, event: QtGui.QMouseEvent) -> None:  # noqa: N802
        if event.button() == QtCore.Qt.MouseButton.LeftButton:
            self.seek_requested.emit(self.t_of(event.position().x()))

    def mouseMoveEvent(self, event: QtGui.QMouseEvent) -> None:  # noqa: N802
        x = event.position().x()
        if event.buttons() & QtCore.Qt.MouseButton.LeftButton:
            self.seek_requested.emit(self.t_of(x))
            return
        t = self.t_of(x)
        self.setToolTip(self.describe(t))

    def describe(self, t: float) -> str:
        """The marks within two pixels of ``t`` and the time, as the tool tip says them."""
        lines = [f"t = {_fmt_time(t - self.start_s)}"]
        data = self.data
        if data is not None:
            w = max(self.width() - LEFT - 4, 1)
            tol = 2.0 * self.duration_s / w
            for mark in data.marks:
                if mark.t0 - tol <= t <= mark.t1 + tol:
                    lines.append(f"{MARK_LABELS[mark.kind]}: {mark.text}")
                    if len(lines) > 8:
                        break
        return "\n".join(lines)


def _right_mid() -> QtCore.Qt.AlignmentFlag:
    return QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter


class TimelineWidget(QtWidgets.QWidget):
    """Transport row over the strip, driving ``player`` (see the module docstring).

    :meth:`refresh` (the window's timer) moves the cursor, takes new timeline data and re-run
    rows, and updates the labels.
    """

    def __init__(self, player: RecordingPlayer, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.player = player
        self.setObjectName("Timeline")
        column = QtWidgets.QVBoxLayout(self)
        column.setContentsMargins(6, 3, 6, 3)
        column.setSpacing(2)
        row = QtWidgets.QHBoxLayout()
        row.setSpacing(3)
        column.addLayout(row)

        def button(text: str, tip: str, slot: Callable[[], None]) -> QtWidgets.QToolButton:
            b = QtWidgets.QToolButton(self)
            b.setText(text)
            b.setToolTip(tip)
            b.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
            b.clicked.connect(slot)
            row.addWidget(b)
            return b

        self.start_button = button(
            "|\u25c0", "to the start (Home)", lambda: self.seek(player.start_s)
        )
        self.back_large = button(
            "\u22121 s", "back 1 s (Shift+Left)", lambda: self.step(-LARGE_STEP_S)
        )
        self.back_small = button(
            "\u2212100 ms", "back 100 ms (Left)", lambda: self.step(-SMALL_STEP_S)
        )
        self.play_button = button("▶ play", "play / pause (Space or K)", self.toggle)
        self.play_button.setMinimumWidth(72)
        self.fwd_small = button(
            "+100 ms", "forward 100 ms (Right)", lambda: self.step(SMALL_STEP_S)
        )
        self.fwd_large = button(
            "+1 s", "forward 1 s (Shift+Right)", lambda: self.step(LARGE_STEP_S)
        )
        self.end_button = button("\u25b6|", "to the end (End)", lambda: self.seek(player.end_s))
        row.addSpacing(8)
        row.addWidget(QtWidgets.QLabel("speed", self))
        self.speed = QtWidgets.QComboBox(self)
        self.speed.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
        for s in SPEEDS:
            self.speed.addItem(f"{s:g}\u00d7", s)
        self.speed.setCurrentIndex(SPEEDS.index(1.0))
        self.speed.setToolTip("playback speed ([ slower, ] faster)")
        self.speed.currentIndexChanged.connect(
            lambda i: player.set_speed(float(self.speed.itemData(i)))
        )
        row.addWidget(self.speed)
        row.addSpacing(8)
        self.time_label = QtWidgets.QLabel(self)
        self.time_label.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        mono = QtGui.QFontDatabase.systemFont(QtGui.QFontDatabase.SystemFont.FixedFont)
        self.time_label.setFont(mono)
        row.addWidget(self.time_label)
        row.addSpacing(8)
        self.legend = QtWidgets.QLabel(self)
        self.legend.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.legend.setText(
            "&nbsp;".join(
                f"<span style='color:{MARK_COLOURS[k]}'>■</span>&nbsp;{MARK_LABELS[k]}"
                for k in MARK_KINDS
            )
            + f"&nbsp;&nbsp;<span style='color:{RERUN_COLOUR}'>—</span>&nbsp;re-run"
        )
        row.addWidget(self.legend)
        row.addStretch(1)
        self.info = QtWidgets.QLabel(self)
        self.info.setStyleSheet("color:#666666;")
        row.addWidget(self.info)

        self.strip = TimelineStrip(player.start_s, player.end_s, self)
        self.strip.seek_requested.connect(self.seek)
        column.addWidget(self.strip)
        self._cameras = tuple(c.name for c in player.layout.cameras)
        self.strip.set_data(player.timeline, self._cameras, player.layout.r_hip_m)
        self._data_id = id(player.timeline)
        self._rerun_key: tuple | None = None
        self.refresh()

    # ----- actions --------------------------------------------------------------------------------
    def seek(self, t: float) -> None:
        self.player.seek(t)
        self.refresh()

    def step(self, dt: float) -> None:
        self.player.step(dt)
        self.refresh()

    def toggle(self) -> None:
        self.player.toggle()
        self.refresh()

    def faster(self, steps: int = 1) -> None:
        i = min(max(self.speed.currentIndex() + steps, 0), self.speed.count() - 1)
        self.speed.setCurrentIndex(i)

    # ----- refresh (window timer) -----------------------------------------------------------------
    def refresh(self) -> None:
        player = self.player
        data = player.timeline
        if id(data) != self._data_id:
            self._data_id = id(data)
            self.strip.set_data(data, self._cameras, player.layout.r_hip_m)
        rerun = player.rerun
        # While it runs, redraw the strip every 1 % of the frames, not every batch.
        step = max(1, rerun.total // 100) if rerun is not None else 1
        key = None if rerun is None else (id(rerun), rerun.done // step, rerun.finished)
        if key != self._rerun_key:
            self._rerun_key = key
            self.strip.set_rerun(rerun)
        pos = player.position
        self.strip.set_cursor(pos)
        playing = player.playing
        text = "❚❚ pause" if playing else "▶ play"
        if self.play_button.text() != text:
            self.play_button.setText(text)
        rel = pos - player.start_s
        self.time_label.setText(f"{_fmt_time(rel)} / {_fmt_time(player.end_s - player.start_s)}")
        info = []
        if not data.complete:
            frac = (data.scanned_s - data.start_s) / max(data.end_s - data.start_s, 1e-9)
            info.append(f"reading timeline {100 * frac:.0f} %")
        if data.error:
            info.append(f"timeline: {data.error}")
        if player.error:
            info.append(player.error)
        view = player.view
        if view is not None and not info:
            info.append(f"seek {view.decode_ms:.0f} ms")
        self.info.setText("  ".join(info))


def install_shortcuts(
    window: QtWidgets.QWidget, timeline: TimelineWidget, *, space: bool = True
) -> list[QtGui.QShortcut]:
    """The timeline's keys on ``window``: Space / K play-pause, Left / Right 100 ms,
    Shift+Left / Shift+Right 1 s, Home / End, [ / ] speed. A text field with focus keeps its
    keys (Qt's shortcut override). ``space=False`` leaves Space to a live window's emergency
    stop."""
    keys: list[tuple[str, Callable[[], None]]] = [
        ("K", timeline.toggle),
        ("Left", lambda: timeline.step(-SMALL_STEP_S)),
        ("Right", lambda: timeline.step(SMALL_STEP_S)),
        ("Shift+Left", lambda: timeline.step(-LARGE_STEP_S)),
        ("Shift+Right", lambda: timeline.step(LARGE_STEP_S)),
        ("Home", lambda: timeline.seek(timeline.player.start_s)),
        ("End", lambda: timeline.seek(timeline.player.end_s)),
        ("[", lambda: timeline.faster(-1)),
        ("]", lambda: timeline.faster(1)),
    ]
    if space:
        keys.append(("Space", timeline.toggle))
    out = []
    for key, slot in keys:
        sc = QtGui.QShortcut(QtGui.QKeySequence(key), window)
        sc.setContext(QtCore.Qt.ShortcutContext.WindowShortcut)
        sc.activated.connect(slot)
        out.append(sc)
    return out


__all__ = [
    "LARGE_STEP_S",
    "MARK_COLOURS",
    "SMALL_STEP_S",
    "TimelineStrip",
    "TimelineWidget",
    "install_shortcuts",
]
