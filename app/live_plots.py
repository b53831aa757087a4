"""Live plots (pyqtgraph) of the recent past carried in each snapshot.

Three stacked plots on one time axis (seconds before the newest frame, so the axis never moves):

* **d_proj (mm)**: each camera's raw 30 Hz estimates (dots), the fused 800 Hz output (line), the
  fusion's regression target before the follower (thin) and the truth (dashed): the paper's
  Fig. 8, live;
* **error vs truth (mm)**: distance from each camera's centroid and from the fused centroid to the
  true closest point;
* **perception latency (ms)**: time per stage A-E and the total, per frame of any camera.

A second tab, **control loop**, plots the session's control snapshots (100 Hz, kept by
:class:`~hapticloud.hardware.live.session.Session`): tick time (µs, newest and longest per
snapshot, the 1250 µs period dashed, a red dot where misses rose), approach velocity (m/s),
constraint force magnitude (N) and the loop's d_proj (mm).

Curves are created once and fed new arrays (``setData``), never re-added; they show only the
history window, so their cost does not grow while the source runs.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from hapticloud.core.perception import STAGES
from hapticloud.hardware.live.contract import CONTROL_COLUMNS, SceneGeometry, Snapshot
from numpy.typing import NDArray
from PyQt6 import QtCore, QtWidgets

from .scene_view import CAMERA_COLOURS, FUSED_COLOUR, TRUTH_COLOUR

STAGE_PENS = ("#8dd3c7", "#bebada", "#fb8072", "#80b1d3", "#fdb462")
WINDOW_S = 8.0  # shown of the HISTORY_S carried


def _finite(x: NDArray, y: NDArray) -> tuple[NDArray, NDArray]:
    keep = np.isfinite(y)
    return x[keep], y[keep]


class LivePlots(QtWidgets.QWidget):
    """d_proj, error against truth and per-stage latency, fed from snapshots."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        pg.setConfigOptions(antialias=False, foreground="#333333", background="w")
        self.tabs = QtWidgets.QTabWidget(self)
        self.tabs.setTabPosition(QtWidgets.QTabWidget.TabPosition.West)
        self.tabs.setDocumentMode(True)
        self.canvas = pg.GraphicsLayoutWidget(self.tabs)
        self.control_canvas = pg.GraphicsLayoutWidget(self.tabs)
        self.tabs.addTab(self.canvas, "perception")
        self.tabs.addTab(self.control_canvas, "control")
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.tabs)
        self.setMinimumHeight(180)
        self.plots: dict[str, pg.PlotItem] = {}
        for row, (key, title) in enumerate(
            (
                ("d_proj", "d_proj (mm)"),
                ("error", "error vs truth (mm)"),
                ("latency", "perception latency (ms)"),
                ("tick", "control tick (µs)"),
                ("approach", "approach (m/s)"),
                ("force", "constraint force (N)"),
                ("loop_d_proj", "loop d_proj (mm)"),
            )
        ):
            canvas = self.canvas if row < 3 else self.control_canvas
            plot = canvas.addPlot(row=0, col=row if row < 3 else row - 3)
            plot.setLabel("left", title)
            plot.setLabel("bottom", "time before now (s)")
            plot.showGrid(x=True, y=True, alpha=0.25)
            plot.setXRange(-WINDOW_S, 0.0, padding=0.01)
            plot.setMouseEnabled(x=False, y=False)
            # The y range is set from the data with each update: pyqtgraph's auto-range works
            # after the data change and costs a second paint (15 ms each in software).
            plot.disableAutoRange()
            plot.hideButtons()
            # Axes keep their rendered pixels between repaints: replaying their tick labels cost
            # ~8 % of a core at 10 plot updates a second in software (py-spy on the app); the
            # x range never moves and the y range moves rarely (hysteresis in _fit_y), and a
            # change repaints them (pyqtgraph calls update(), which drops the cache).
            for side in ("left", "bottom"):
                plot.getAxis(side).setCacheMode(
                    QtWidgets.QGraphicsItem.CacheMode.DeviceCoordinateCache
                )
            self.plots[key] = plot
        self._curves: dict[str, pg.PlotDataItem] = {}
        self._control: dict[str, pg.PlotDataItem] = {}
        self._build_control()
        self._camera_names: tuple[str, ...] = ()
        self._shown_seq = -1
        self.updates = 0
        self.control_updates = 0

    def _build_control(self) -> None:
        """The control tab's curves, once (they do not depend on the scene)."""
        legend = {"offset": (2, 2), "labelTextSize": "7pt", "brush": (255, 255, 255, 170)}
        tick = self.plots["tick"]
        tick.addLegend(colCount=4, **legend)

        def add(key: str, plot: str, **kwargs: object) -> None:
            curve = self.plots[plot].plot([], [], **kwargs)
            curve.setClipToView(True)
            self._control[key] = curve

        add(
            "period",
            "tick",
            pen=pg.mkPen("#b00020", width=1, style=QtCore.Qt.PenStyle.DashLine),
            name="period",
        )
        add("tick_us_max", "tick", pen=pg.mkPen("#fdb462", width=1), name="max")
        add("tick_us", "tick", pen=pg.mkPen("#1f78b4", width=1.5), name="tick")
        add(
            "misses",
            "tick",
            pen=None,
            symbol="o",
            symbolSize=6,
            symbolPen=None,
            symbolBrush="#b00020",
            name="miss",
        )
        add("approach_mps", "approach", pen=pg.mkPen("#6a3d9a", width=1.5))
        add("force_n", "force", pen=pg.mkPen("#d95f02", width=1.5))
        add("d_proj_mm", "loop_d_proj", pen=pg.mkPen(FUSED_COLOUR, width=1.5))

    def set_geometry(self, geometry: SceneGeometry) -> None:
        """Create the curves for the cameras of ``geometry`` (once per source)."""
        for key in ("d_proj", "error", "latency"):
            plot = self.plots[key]
            plot.clear()
            if plot.legend is not None:
                plot.legend.scene().removeItem(plot.legend)
                plot.legend = None
        self._curves.clear()
        self._camera_names = tuple(cam.name for cam in geometry.cameras)
        d_proj, error, latency = self.plots["d_proj"], self.plots["error"], self.plots["latency"]
        # Compact, translucent legends: the newest data (right edge) stays visible under them.
        legend = {"offset": (2, 2), "labelTextSize": "7pt", "brush": (255, 255, 255, 170)}
        d_proj.addLegend(colCount=3, **legend)
        error.addLegend(colCount=3, **legend)
        latency.addLegend(colCount=3, **legend)
        self._add(
            "truth",
            d_proj,
            pen=pg.mkPen(TRUTH_COLOUR, width=1.5, style=QtCore.Qt.PenStyle.DashLine),
            name="truth",
        )
        self._add("target", d_proj, pen=pg.mkPen("#999999", width=1), name="regression")
        self._add("fused", d_proj, pen=pg.mkPen(FUSED_COLOUR, width=2), name="fused 800 Hz")
        for i, name in enumerate(self._camera_names):
            colour = CAMERA_COLOURS[i % len(CAMERA_COLOURS)]
            self._add(
                f"raw:{name}",
                d_proj,
                pen=None,
                symbol="o",
                symbolSize=4,
                symbolPen=None,
                symbolBrush=colour,
                name=name,
            )
            self._add(f"err:{name}", error, pen=pg.mkPen(colour, width=1), name=name)
        self._add("err:fused", error, pen=pg.mkPen(FUSED_COLOUR, width=2), name="fused")
        for stage, colour in zip(STAGES, STAGE_PENS, strict=True):
            self._add(f"ms:{stage}", latency, pen=pg.mkPen(colour, width=1), name=stage)
        self._add("ms:total", latency, pen=pg.mkPen("#333333", width=1.5), name="total")
        self._shown_seq = -1

    def _add(self, key: str, plot: pg.PlotItem, **kwargs: object) -> None:
        curve = plot.plot([], [], **kwargs)
        curve.setClipToView(True)
        curve.setDownsampling(auto=True, method="peak")
        self._curves[key] = curve

    def show_control(self, history: NDArray) -> None:
        """Feed the control tab from a session's history (:data:`CONTROL_COLUMNS` rows)."""
        if not len(history):
            return
        col = {name: history[:, i] for i, name in enumerate(CONTROL_COLUMNS)}
        x = col["t"] - col["t"][-1]
        recent = x >= -WINDOW_S
        self._control["period"].setData([-WINDOW_S, 0.0], [1250.0, 1250.0])
        for key in ("tick_us", "tick_us_max", "approach_mps", "force_n", "d_proj_mm"):
            self._control[key].setData(x, col[key], connect="finite")
        rose = np.flatnonzero(np.diff(col["misses"]) > 0) + 1
        self._control["misses"].setData(x[rose], col["tick_us_max"][rose])
        for plot, keys in (
            ("tick", ("tick_us", "tick_us_max")),
            ("approach", ("approach_mps",)),
            ("force", ("force_n",)),
            ("loop_d_proj", ("d_proj_mm",)),
        ):
            parts = [col[k][recent & np.isfinite(col[k])] for k in keys]
            self._fit_y(plot, parts)
        self.control_updates += 1

    def curve_count(self) -> int:
        """Curves in the plots (the frame-update test checks this never grows)."""
        return sum(len(plot.listDataItems()) for plot in self.plots.values())

    def show_snapshot(self, snap: Snapshot) -> None:
        """Feed every curve from ``snap.history`` (skipped if this snapshot was shown)."""
        if snap.seq == self._shown_seq or not self._curves:
            return
        self._shown_seq = snap.seq
        hist = snap.history
        now = snap.t
        frames = hist.frames
        ranges: dict[str, list[NDArray]] = {key: [] for key in self.plots}
        if len(frames):
            ft = hist.frame("t") - now
            cam = hist.frame("camera")

            def put(key: str, plot: str, x: NDArray, y: NDArray) -> None:
                x, y = _finite(x, y)
                self._curves[key].setData(x, y)
                ranges[plot].append(y[x >= -WINDOW_S])

            put("truth", "d_proj", ft, hist.frame("true_d_proj_mm"))
            put("err:fused", "error", ft, hist.frame("fused_error_mm"))
            for i, name in enumerate(self._camera_names):
                mine = cam == i
                put(f"raw:{name}", "d_proj", ft[mine], hist.frame("d_proj_mm")[mine])
                put(f"err:{name}", "error", ft[mine], hist.frame("error_mm")[mine])
            for stage in (*STAGES, "total"):
                put(f"ms:{stage}", "latency", ft, hist.frame(f"{stage}_ms"))
        ticks = hist.ticks
        if len(ticks):
            tt = ticks[:, 0] - now
            # NaN breaks the line where the fusion was invalid, instead of bridging the gap.
            for key, column in (("fused", "d_proj_mm"), ("target", "target_d_proj_mm")):
                y = hist.tick(column)
                self._curves[key].setData(tt, y, connect="finite")
                ranges["d_proj"].append(y[(tt >= -WINDOW_S) & np.isfinite(y)])
        for key, parts in ranges.items():
            self._fit_y(key, parts)
        self.updates += 1

    def _fit_y(self, key: str, parts: list[NDArray]) -> None:
        """Set the y range from the data, with hysteresis.

        A range change makes every clipped/downsampled curve recompute and costs a second paint,
        so the range grows at once when the data leaves it but shrinks only when the data uses
        less than half of it.
        """
        values = np.concatenate(parts) if parts else np.empty(0)
        if not len(values):
            return
        lo, hi = float(values.min()), float(values.max())
        if key not in ("d_proj", "loop_d_proj", "approach"):
            lo = min(lo, 0.0)  # errors and latencies: keep zero in view
        (cur_lo, cur_hi) = self.plots[key].viewRange()[1]
        inside = cur_lo <= lo and hi <= cur_hi
        if inside and (hi - lo) > 0.5 * (cur_hi - cur_lo):
            return
        pad = max(0.15 * (hi - lo), 0.5)
        self.plots[key].setYRange(lo - pad, hi + pad, padding=0.0)
