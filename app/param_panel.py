"""The parameter panel, generated from a root :class:`~hapticloud.core.config.StageConfig`.

Nothing here names a parameter of the pipeline: every row comes from ``Root.params()`` (path,
kind, default, range, unit, doc, choices, log scale). The mapping from a :class:`ParamInfo` to
a widget is:

* ``bool`` -> check box; ``str`` with ``choices`` -> combo box;
* ``int`` / ``float`` -> :class:`NumberEditor`: a superqt ``QDoubleSlider`` next to a spin box
  with the unit as suffix. The spin box accepts the whole validated range; the slider covers a
  useful span around the default (the full range of, say, ``min_cluster_points`` is 1..10^6), on
  a log10 scale when the parameter says ``log_scale`` or when the span covers three decades;
* a ``r_in_m`` / ``r_out_m`` pair of one table -> one superqt ``QLabeledDoubleRangeSlider``;
* anything else (lists of numbers) -> a line edit read as TOML.

A change is validated by building the new root with :meth:`StageConfig.replace_path`. A valid
one replaces the panel's config and is emitted (:attr:`ParamPanel.config_changed`) for the
source to apply at its next frame; an invalid one is refused: the widget reverts to the value in
effect, the one-line reason is shown inline and emitted (:attr:`ParamPanel.refused`), nothing is
applied. While a slider is dragged every valid position is applied at once (tuning is watching
the effect); the change log gets one line per committed change (release, Enter, click).
"""

from __future__ import annotations

import math
import time
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hapticloud.assets import asset_path
from hapticloud.core.config import ParamInfo, StageConfig
from hapticloud.core.errors import ConfigError
from PyQt6 import QtCore, QtGui, QtWidgets
from superqt import QCollapsible, QDoubleSlider, QLabeledDoubleRangeSlider

#: Section titles by table path; tables not named here are titled by their key.
SECTION_TITLES: Mapping[str, str] = {
    "perception": "Perception",
    "perception.crop": "A · crop (workspace sphere, robot)",
    "perception.voxel": "B · voxel filter",
    "perception.cluster": "C · clusters",
    "perception.reconstruction": "D · reconstruction (ICP memory)",
    "perception.abstraction": "E · abstraction (surface estimate)",
    "perception.abstraction.quadric": "E · curvature-aware estimator",
    "perception.": "pipeline",
    "fusion": "Fusion / PID",
    "fusion.": "regression",
    "haptics": "Haptics",
    "haptics.": "constraints",
    "haptics.positional": "positional constraint (eqs. 9-11)",
    "haptics.velocity": "velocity constraint (eqs. 12-14)",
    "haptics.force": "force constraint (ISO/TS 15066)",
    "controller": "Controller",
    "controller.": "hierarchy",
    "controller.equation_of_motion": "1 · equation of motion",
    "controller.position_limit": "2 · joint position limits",
    "controller.velocity_limit": "2 · joint velocity limits",
    "controller.torque_limit": "torque limits",
    "controller.walls": "3 · fixed walls",
    "controller.min_acceleration": "5 · minimal acceleration",
    "controller.solver": "solver (DAQP)",
}
#: Leaves that open a new section inside a flat table (``FusionConfig`` has no sub-tables).
SECTION_BREAKS: Mapping[str, str] = {"fusion.feedforward": "PID follower"}
#: Sections shown collapsed at first (rarely tuned).
COLLAPSED: frozenset[str] = frozenset({"perception.abstraction.quadric"})
#: Pairs of parameters of one table edited with one range slider.
RANGE_PAIRS: tuple[tuple[str, str], ...] = (("r_in_m", "r_out_m"),)

_UNIT_SUFFIXES = (
    "_rad_s2",
    "_rad_s",
    "_m_s2",
    "_m_s",
    "_mps",
    "_deg",
    "_ms",
    "_hz",
    "_m",
    "_s",
)
_ERROR_STYLE = "color: #b00020; font-weight: 600;"
_LOG_LIMIT = 500  # change-log rows kept


def pretty_name(name: str) -> str:
    """``voxel_size_m`` -> ``voxel size`` (the unit is shown next to the value)."""
    for suffix in _UNIT_SUFFIXES:
        if name.endswith(suffix):
            name = name[: -len(suffix)]
            break
    return name.replace("_", " ")


def format_value(value: Any, unit: str = "") -> str:
    """A value as the change log and messages show it (4 significant digits, with its unit)."""
    if isinstance(value, bool) or value is None:
        text = str(value).lower()
    elif isinstance(value, float):
        text = f"{value:.4g}"
    elif isinstance(value, tuple):
        text = "[" + ", ".join(f"{v:.4g}" for v in value) + "]"
    else:
        text = str(value)
    return f"{text} {unit}" if unit and not isinstance(value, bool | str) else text


def _tooltip(info: ParamInfo) -> str:
    lo = "-inf" if info.lo is None else format_value(info.lo)
    hi = "inf" if info.hi is None else format_value(info.hi)
    rng = f"[{lo}, {hi}] {info.unit}".rstrip() if info.kind in (int, float) else ""
    lines = [f"<b>{info.path}</b>", info.doc]
    if info.choices:
        lines.append("one of: " + ", ".join(info.choices))
    if rng:
        lines.append(f"range {rng}")
    lines.append(f"default {format_value(info.default, info.unit)}")
    return "<br>".join(line for line in lines if line)


# ----- editors ------------------------------------------------------------------------------------


class Editor(QtWidgets.QWidget):
    """One parameter's widget. ``edited(value, final)``: ``final`` False while dragging."""

    edited = QtCore.pyqtSignal(object, bool)

    def __init__(self, info: ParamInfo, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.info = info
        self.setToolTip(_tooltip(info))

    def value(self) -> Any:
        raise NotImplementedError

    def set_value(self, value: Any) -> None:
        """Show ``value`` without emitting :attr:`edited`."""
        raise NotImplementedError


class BoolEditor(Editor):
    def __init__(self, info: ParamInfo, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(info, parent)
        self.box = QtWidgets.QCheckBox(self)
        _single(self, self.box)
        self.box.toggled.connect(lambda on: self.edited.emit(bool(on), True))

    def value(self) -> bool:
        return self.box.isChecked()

    def set_value(self, value: Any) -> None:
        with QtCore.QSignalBlocker(self.box):
            self.box.setChecked(bool(value))


class ChoiceEditor(Editor):
    def __init__(self, info: ParamInfo, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(info, parent)
        self.combo = QtWidgets.QComboBox(self)
        self.combo.addItems(list(info.choices or ()))
        _single(self, self.combo)
        self.combo.currentTextChanged.connect(lambda text: self.edited.emit(text, True))

    def value(self) -> str:
        return self.combo.currentText()

    def set_value(self, value: Any) -> None:
        with QtCore.QSignalBlocker(self.combo):
            self.combo.setCurrentText(str(value))


class TextEditor(Editor):
    """Fallback: the value typed as a TOML literal (``[0.01, 0.02]``, ``"text"``)."""

    def __init__(self, info: ParamInfo, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(info, parent)
        self.line = QtWidgets.QLineEdit(self)
        _single(self, self.line)
        self.line.editingFinished.connect(self._commit)

    def _commit(self) -> None:
        text = self.line.text().strip()
        try:
            value: Any = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            value = text
        self.edited.emit(tuple(value) if isinstance(value, list) else value, True)

    def value(self) -> Any:
        return self.line.text()

    def set_value(self, value: Any) -> None:
        with QtCore.QSignalBlocker(self.line):
            self.line.setText(format_value(value))


def _decimals(info: ParamInfo) -> int:
    """Enough decimals for 3 significant digits of the default, and to show it exactly."""
    default = info.default if isinstance(info.default, int | float) else 0.0
    magnitude = abs(float(default)) or abs(float(info.hi or 1.0)) or 1.0
    significant = 2 - math.floor(math.log10(magnitude))
    text = repr(float(default))
    exact = len(text.split(".")[1].rstrip("0")) if "." in text and "e" not in text else 0
    return max(0, min(8, max(significant, exact)))


class ScientificEditor(TextEditor):
    """A float too small for a spin box's decimals, typed in scientific notation (``1e-9``)."""

    def value(self) -> Any:
        try:
            return float(self.line.text())
        except ValueError:
            return self.line.text()


@dataclass(frozen=True)
class SliderSpan:
    """The part of a parameter's range the slider covers, and how."""

    lo: float
    hi: float
    log: bool

    def to_slider(self, value: float) -> float:
        value = min(max(value, self.lo), self.hi)
        return math.log10(value) if self.log else value

    def from_slider(self, position: float) -> float:
        return 10.0**position if self.log else position


def slider_span(info: ParamInfo) -> SliderSpan | None:
    """A useful slider span for ``info``, or ``None`` when there is none (spin box only).

    Log scale for ``log_scale`` parameters and for positive ranges over three decades, clipped to
    two decades either side of the default; linear otherwise, clipped to ten times the default's
    size when the range is much wider.
    """
    lo, hi, default = info.lo, info.hi, float(info.default)
    positive_lo = lo is not None and lo > 0
    wide = positive_lo and hi is not None and hi / lo >= 1e3
    if (info.log_scale or wide) and default > 0:
        s_lo = max(lo if positive_lo else 0.0, default / 100.0)
        s_hi = min(hi if hi is not None else math.inf, default * 100.0)
        return SliderSpan(s_lo, s_hi, True) if s_hi > s_lo else None
    if lo is None and hi is None:
        return None
    scale = abs(default)
    s_lo = lo if lo is not None else default - 10 * scale
    s_hi = hi if hi is not None else default + 10 * scale
    if scale > 0 and s_hi - s_lo > 20 * scale:
        s_hi = min(s_hi, max(s_lo + 10 * scale, default * 10.0))
    elif scale == 0 and s_hi - s_lo > 1e3:
        return None  # e.g. an integral gain 0..1e8 at 0: no span says anything; type it
    return SliderSpan(s_lo, s_hi, False) if s_hi > s_lo else None


class NumberEditor(Editor):
    """Slider (useful span, linear or log) + spin box (full range, unit suffix)."""

    STEPS = 1000  # slider resolution over its span

    def __init__(self, info: ParamInfo, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(info, parent)
        self.is_int = info.kind is int
        layout = QtWidgets.QHBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.setSpacing(6)
        self.span = slider_span(info)
        self.slider: QDoubleSlider | None = None
        if self.span is not None:
            slider = QDoubleSlider(QtCore.Qt.Orientation.Horizontal, self)
            a, b = self.span.to_slider(self.span.lo), self.span.to_slider(self.span.hi)
            slider.setRange(a, b)
            slider.setSingleStep((b - a) / self.STEPS)
            slider.setMinimumWidth(50)
            layout.addWidget(slider, 1)
            slider.valueChanged.connect(self._slider_moved)
            slider.sliderReleased.connect(self._slider_released)
            self.slider = slider
        spin: QtWidgets.QAbstractSpinBox
        lo = -1e12 if info.lo is None else info.lo
        hi = 1e12 if info.hi is None else info.hi
        if self.is_int:
            spin = QtWidgets.QSpinBox(self)
            spin.setRange(int(max(lo, -(2**31) + 1)), int(min(hi, 2**31 - 1)))
        else:
            spin = QtWidgets.QDoubleSpinBox(self)
            spin.setDecimals(_decimals(info))
            spin.setRange(lo, hi)
            spin.setStepType(QtWidgets.QAbstractSpinBox.StepType.AdaptiveDecimalStepType)
        if info.unit:
            spin.setSuffix(f" {info.unit}")
        spin.setKeyboardTracking(False)  # one change per Enter / focus-out, not per keystroke
        spin.setMinimumWidth(92)
        spin.setAlignment(QtCore.Qt.AlignmentFlag.AlignRight)
        spin.valueChanged.connect(self._spin_changed)
        layout.addWidget(spin, 0 if self.slider is not None else 1)
        self.spin = spin

    def _cast(self, value: float) -> float | int:
        return round(value) if self.is_int else float(value)

    def _slider_moved(self, position: float) -> None:
        assert self.span is not None and self.slider is not None
        value = self._cast(self.span.from_slider(position))
        with QtCore.QSignalBlocker(self.spin):
            self.spin.setValue(value)
        self.edited.emit(value, not self.slider.isSliderDown())

    def _slider_released(self) -> None:
        self.edited.emit(self._cast(self.spin.value()), True)

    def _spin_changed(self, value: float) -> None:
        self._show_on_slider(value)
        self.edited.emit(self._cast(value), True)

    def _show_on_slider(self, value: float) -> None:
        if self.slider is not None and self.span is not None:
            with QtCore.QSignalBlocker(self.slider):
                self.slider.setValue(self.span.to_slider(float(value)))

    def value(self) -> float | int:
        return self._cast(self.spin.value())

    def set_value(self, value: Any) -> None:
        with QtCore.QSignalBlocker(self.spin):
            self.spin.setValue(value)
        self._show_on_slider(value)


class RangeEditor(QtWidgets.QWidget):
    """Two parameters (``lo_info``, ``hi_info``) on one labelled range slider."""

    edited = QtCore.pyqtSignal(object, bool)

    def __init__(
        self, lo_info: ParamInfo, hi_info: ParamInfo, parent: QtWidgets.QWidget | None = None
    ) -> None:
        super().__init__(parent)
        self.infos = (lo_info, hi_info)
        self.setToolTip(_tooltip(lo_info) + "<hr>" + _tooltip(hi_info))
        self.slider = QLabeledDoubleRangeSlider(QtCore.Qt.Orientation.Horizontal, self)
        lo = min(v for v in (lo_info.lo, hi_info.lo) if v is not None)
        hi = max(v for v in (lo_info.hi, hi_info.hi) if v is not None)
        # The useful span: up to 4x the default outer radius (the full range is 0.5-1 m).
        hi = min(hi, 4.0 * float(hi_info.default))
        self.slider.setRange(lo, hi)
        self.slider.setDecimals(max(_decimals(lo_info), _decimals(hi_info)))
        self.slider.setSingleStep((hi - lo) / 1000)
        # Values in editable boxes at both ends, none over the handles: handle labels collide
        # when r_in and r_out are close.
        self.slider.setHandleLabelPosition(QLabeledDoubleRangeSlider.LabelPosition.NoLabel)
        self.slider.setEdgeLabelMode(QLabeledDoubleRangeSlider.EdgeLabelMode.LabelIsValue)
        if lo_info.unit:
            for label in (self.slider._min_label, self.slider._max_label):  # no public accessor
                label.setSuffix(f" {lo_info.unit}")
        _single(self, self.slider)
        self._down = False
        self.slider.sliderPressed.connect(self._pressed)
        self.slider.sliderReleased.connect(self._released)
        self.slider.valueChanged.connect(self._changed)

    def _pressed(self) -> None:
        self._down = True

    def _released(self) -> None:
        self._down = False
        self.edited.emit(self.value(), True)

    def _changed(self, values: tuple[float, float]) -> None:
        self.edited.emit((float(values[0]), float(values[1])), not self._down)

    def value(self) -> tuple[float, float]:
        a, b = self.slider.value()
        return float(a), float(b)

    def set_value(self, value: tuple[float, float]) -> None:
        with QtCore.QSignalBlocker(self.slider):
            self.slider.setValue(tuple(value))


def _single(parent: QtWidgets.QWidget, child: QtWidgets.QWidget) -> None:
    layout = QtWidgets.QHBoxLayout(parent)
    layout.setContentsMargins(0, 0, 0, 0)
    layout.addWidget(child)


def make_editor(info: ParamInfo, parent: QtWidgets.QWidget | None = None) -> Editor:
    """The widget for one parameter, chosen from its kind, range and choices."""
    if info.kind is bool:
        return BoolEditor(info, parent)
    if info.choices:
        return ChoiceEditor(info, parent)
    if info.kind is float and isinstance(info.default, float) and 0 < abs(info.default) < 1e-6:
        # A spin box shows at most 8 decimals: a solver tolerance of 1e-9 would read 0.
        return ScientificEditor(info, parent)
    if info.kind in (int, float) and isinstance(info.default, int | float):
        return NumberEditor(info, parent)
    return TextEditor(info, parent)


# ----- change log ---------------------------------------------------------------------------------


class ChangeLog(QtWidgets.QTreeWidget):
    """What changed when: time, parameter, old -> new (refusals in red)."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.setColumnCount(3)
        self.setHeaderLabels(["time", "parameter", "change"])
        self.setRootIsDecorated(False)
        self.setUniformRowHeights(True)
        self.setAlternatingRowColors(True)
        header = self.header()
        header.setStretchLastSection(True)
        header.setSectionResizeMode(0, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(1, QtWidgets.QHeaderView.ResizeMode.Interactive)
        self.setColumnWidth(1, 170)
        self.entries: list[tuple[float, str, str]] = []

    def add(self, what: str, change: str, *, error: bool = False) -> None:
        stamp = time.time()
        self.entries.append((stamp, what, change))
        # Shown: the parameter's table and name ("voxel.voxel_size_m"); the tool tip has it all.
        short = " + ".join(".".join(p.split(".")[-2:]) for p in what.split(" + "))
        item = QtWidgets.QTreeWidgetItem(
            [time.strftime("%H:%M:%S", time.localtime(stamp)), short, change]
        )
        item.setToolTip(1, what)
        item.setToolTip(2, change)
        if error:
            for col in range(3):
                item.setForeground(col, QtGui.QBrush(QtGui.QColor("#b00020")))
        self.insertTopLevelItem(0, item)  # newest on top
        while self.topLevelItemCount() > _LOG_LIMIT:
            self.takeTopLevelItem(self.topLevelItemCount() - 1)


# ----- the panel ----------------------------------------------------------------------------------


@dataclass
class _Row:
    paths: tuple[str, ...]
    editor: Editor | RangeEditor
    label: QtWidgets.QLabel
    committed: Any  # value at the last commit (the change log's "old")


def _table_of(path: str) -> str:
    return path.rpartition(".")[0]


def _group_rows(infos: Iterable[ParamInfo]) -> list[tuple[str, list[ParamInfo]]]:
    """Parameters grouped by section (a table, or a part of a flat table), declaration order."""
    sections: list[tuple[str, list[ParamInfo]]] = []
    for info in infos:
        table = _table_of(info.path)
        key = SECTION_BREAKS.get(info.path)
        if key is not None:
            key = f"{table}:{key}"
        elif sections and sections[-1][0].startswith(f"{table}:"):
            key = sections[-1][0]  # still in the section a break opened
        else:
            key = table
        if not sections or sections[-1][0] != key:
            sections.append((key, []))
        sections[-1][1].append(info)
    return sections


class ParamPanel(QtWidgets.QWidget):
    """Generated parameter panel with presets and a change log.

    Parameters
    ----------
    config
        The root configuration in effect (its class gives the parameters).
    """

    #: The new root config (validated), after a change was accepted.
    config_changed = QtCore.pyqtSignal(object)
    #: The one-line reason a change was refused.
    refused = QtCore.pyqtSignal(str)

    def __init__(self, config: StageConfig, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self._config = config
        self._root = type(config)
        self._infos = {info.path: info for info in self._root.params()}
        self._rows: dict[str, _Row] = {}
        self._pending_drag: dict[str, Any] = {}
        self._tab_columns: dict[str, QtWidgets.QVBoxLayout] = {}
        self._notes: dict[str, QtWidgets.QLabel] = {}

        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.setSpacing(4)
        layout.addLayout(self._preset_bar())
        self.error_label = QtWidgets.QLabel(self)
        self.error_label.setWordWrap(True)
        self.error_label.setStyleSheet(_ERROR_STYLE)
        self.error_label.setVisible(False)
        layout.addWidget(self.error_label)

        splitter = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical, self)
        self.tabs = QtWidgets.QTabWidget(splitter)
        self.change_log = ChangeLog(splitter)
        splitter.addWidget(self.tabs)
        splitter.addWidget(self.change_log)
        splitter.setStretchFactor(0, 3)
        splitter.setStretchFactor(1, 1)
        splitter.setCollapsible(0, False)
        layout.addWidget(splitter, 1)
        self._build_tabs()
        self._refresh_labels()

    # ----- building ---------------------------------------------------------------------------
    def _preset_bar(self) -> QtWidgets.QHBoxLayout:
        bar = QtWidgets.QHBoxLayout()
        for text, tip, slot in (
            ("Load…", "load a preset (TOML); missing keys take their defaults", self._ask_load),
            ("Save…", "save every parameter as a TOML preset", self._ask_save),
            ("Defaults", "reset every parameter to its shipped default", self.reset_defaults),
        ):
            button = QtWidgets.QPushButton(text, self)
            button.setToolTip(tip)
            button.clicked.connect(slot)
            bar.addWidget(button)
        bar.addWidget(self._shipped_presets())
        bar.addStretch(1)
        return bar

    def _shipped_presets(self) -> QtWidgets.QToolButton:
        """The presets hapticloud ships (assets/presets: fast, balanced, accurate; made by
        ``hapticloud study``, docs/trade-study.md)."""
        button = QtWidgets.QToolButton(self)
        button.setText("Presets")
        button.setToolTip("shipped presets from the speed/accuracy study (docs/trade-study.md)")
        button.setPopupMode(QtWidgets.QToolButton.ToolButtonPopupMode.InstantPopup)
        menu = QtWidgets.QMenu(button)
        for path in sorted(asset_path("presets").glob("*.toml")):
            action = menu.addAction(path.stem)
            action.triggered.connect(lambda _=False, p=path: self.load_preset(p))
        button.setMenu(menu)
        self.shipped_presets = menu
        return button

    def _build_tabs(self) -> None:
        by_top: dict[str, list[ParamInfo]] = {}
        for info in self._infos.values():
            top = info.path.split(".")[0] if "." in info.path else ""
            by_top.setdefault(top, []).append(info)
        for top, infos in by_top.items():
            scroll = QtWidgets.QScrollArea(self.tabs)
            scroll.setWidgetResizable(True)
            scroll.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
            # Rows shrink to the dock's width; a sideways scroll bar hides the values.
            scroll.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
            inner = QtWidgets.QWidget(scroll)
            column = QtWidgets.QVBoxLayout(inner)
            column.setContentsMargins(2, 2, 2, 2)
            column.setSpacing(2)
            for key, members in _group_rows(infos):
                column.addWidget(self._section(top, key, members, inner))
            column.addStretch(1)
            scroll.setWidget(inner)
            self.tabs.addTab(scroll, SECTION_TITLES.get(top, top or "general"))
            self._tab_columns[top] = column

    def _section_title(self, top: str, key: str) -> str:
        if ":" in key:
            return key.split(":", 1)[1]
        if key == top:
            return SECTION_TITLES.get(f"{top}.", "general")
        return SECTION_TITLES.get(key, key.removeprefix(f"{top}."))

    def _section(
        self, top: str, key: str, infos: list[ParamInfo], parent: QtWidgets.QWidget
    ) -> QtWidgets.QWidget:
        box = QCollapsible(self._section_title(top, key), parent)
        body = QtWidgets.QWidget(box)
        form = QtWidgets.QFormLayout(body)
        form.setContentsMargins(14, 0, 2, 4)
        form.setHorizontalSpacing(8)
        form.setVerticalSpacing(3)
        form.setFieldGrowthPolicy(QtWidgets.QFormLayout.FieldGrowthPolicy.AllNonFixedFieldsGrow)
        names = {info.name: info for info in infos}
        used: set[str] = set()
        for info in infos:
            if info.name in used:
                continue
            pair = next(
                (p for p in RANGE_PAIRS if info.name in p and all(n in names for n in p)), None
            )
            if pair is not None:
                lo_info, hi_info = names[pair[0]], names[pair[1]]
                editor: Editor | RangeEditor = RangeEditor(lo_info, hi_info, body)
                paths = (lo_info.path, hi_info.path)
                text = f"{pretty_name(lo_info.name)} \u2013 {pretty_name(hi_info.name)}"
                unit = lo_info.unit
                used.update(pair)
            else:
                editor = make_editor(info, body)
                paths = (info.path,)
                text = pretty_name(info.name)
                unit = ""  # the spin box carries it
                used.add(info.name)
            label = QtWidgets.QLabel(f"{text} ({unit})" if unit else text, body)
            label.setToolTip(editor.toolTip())
            if isinstance(editor, RangeEditor):
                form.addRow(label)  # the range slider gets the full width on its own row
                form.addRow(editor)
            else:
                form.addRow(label, editor)
            row = _Row(paths, editor, label, self._current(paths))
            editor.set_value(row.committed)
            editor.edited.connect(lambda value, final, r=row: self._on_edit(r, value, final))
            for path in paths:
                self._rows[path] = row
        box.addWidget(body)
        if key in COLLAPSED:
            box.collapse(animate=False)
        else:
            box.expand(animate=False)
        return box

    def set_table_note(self, top: str, note: str, *, read_only: bool) -> None:
        """Show ``note`` at the top of table ``top``'s tab; ``read_only`` disables its editors
        (values shown, not changeable: e.g. nobody can apply them while the app runs)."""
        column = self._tab_columns[top]
        label = self._notes.get(top)
        if label is None:
            label = QtWidgets.QLabel(column.parentWidget())
            label.setWordWrap(True)
            label.setStyleSheet("color:#7a5b00; background:#fff3cd; padding:3px;")
            column.insertWidget(0, label)
            self._notes[top] = label
        label.setText(note)
        label.setVisible(bool(note))
        for path, row in self._rows.items():
            if path.startswith(f"{top}."):
                row.editor.setEnabled(not read_only)

    def table_note(self, top: str) -> str:
        """The note shown on table ``top``'s tab ("" for none)."""
        label = self._notes.get(top)
        return label.text() if label is not None else ""

    def table_read_only(self, top: str) -> bool:
        rows = [r for p, r in self._rows.items() if p.startswith(f"{top}.")]
        return bool(rows) and not any(r.editor.isEnabled() for r in rows)

    # ----- values -----------------------------------------------------------------------------
    @property
    def config(self) -> StageConfig:
        """The configuration in effect (last accepted)."""
        return self._config

    def editor(self, path: str) -> Editor | RangeEditor:
        """The widget editing ``path`` (a range editor is shared by its pair)."""
        return self._rows[path].editor

    def paths(self) -> tuple[str, ...]:
        return tuple(self._rows)

    def _current(self, paths: tuple[str, ...]) -> Any:
        values = tuple(self._config.get_path(p) for p in paths)
        return values[0] if len(values) == 1 else values

    def _build(self, paths: tuple[str, ...], value: Any) -> StageConfig:
        """The root with ``paths`` set to ``value``; raises :class:`ConfigError`."""
        if len(paths) == 1:
            return self._config.replace_path(paths[0], value)
        # A pair: set it in the order that keeps lo < hi in between (either may move first).
        values = dict(zip(paths, value, strict=True))
        try:
            return self._config.with_overrides(values)
        except ConfigError as first:
            try:
                return self._config.with_overrides(dict(reversed(list(values.items()))))
            except ConfigError:
                raise first from None

    def set_value(self, path: str, value: Any) -> bool:
        """Change one parameter as the user would (validated, logged); True if accepted."""
        row = self._rows[path]
        if len(row.paths) > 1:
            current = list(self._current(row.paths))
            current[row.paths.index(path)] = value
            value = tuple(current)
        row.editor.set_value(value)
        return self._on_edit(row, value, True)

    def _on_edit(self, row: _Row, value: Any, final: bool) -> bool:
        old = self._current(row.paths)
        try:
            new = self._build(row.paths, value)
        except ConfigError as err:
            self._show_error(str(err))
            if final:
                row.editor.set_value(old)  # back to the value in effect
                self.change_log.add(" + ".join(row.paths), f"refused: {err}", error=True)
                self._log_commit(row)
            return False
        self._clear_error()
        if new != self._config:
            self._config = new
            self.config_changed.emit(new)
        if final:
            self._log_commit(row)
        self._refresh_labels(row)
        return True

    def _log_commit(self, row: _Row) -> None:
        now = self._current(row.paths)
        if now != row.committed:
            unit = self._infos[row.paths[0]].unit
            change = f"{format_value(row.committed, unit)} → {format_value(now, unit)}"
            self.change_log.add(" + ".join(row.paths), change)
            row.committed = now

    def _show_error(self, reason: str) -> None:
        self.error_label.setText(f"Refused: {reason}")
        self.error_label.setVisible(True)
        self.refused.emit(reason)

    def _clear_error(self) -> None:
        if not self.error_label.isHidden():
            self.error_label.setVisible(False)

    def _refresh_labels(self, only: _Row | None = None) -> None:
        """Bold labels mark values that differ from the shipped defaults."""
        rows = (
            [only] if only is not None else list({id(r): r for r in self._rows.values()}.values())
        )
        for row in rows:
            changed = any(self._config.get_path(p) != self._infos[p].default for p in row.paths)
            font = row.label.font()
            font.setBold(changed)
            row.label.setFont(font)

    # ----- whole configurations ------------------------------------------------------------------
    def set_config(self, config: StageConfig, what: str) -> None:
        """Replace every value (preset, defaults) and log it as one change named ``what``."""
        if not isinstance(config, self._root):
            raise ConfigError(f"expected a {self._root.__name__}, got {type(config).__name__}")
        changed = [p for p in self._infos if config.get_path(p) != self._config.get_path(p)]
        self._config = config
        for row in {id(r): r for r in self._rows.values()}.values():
            row.committed = self._current(row.paths)
            row.editor.set_value(row.committed)
        self._clear_error()
        self._refresh_labels()
        self.change_log.add(what, f"{len(changed)} parameter(s) changed")
        self.config_changed.emit(config)

    def reset_defaults(self) -> None:
        self.set_config(self._root(), "reset to defaults")

    def save_preset(self, path: str | Path) -> None:
        self._config.save(path)
        self.change_log.add("preset saved", str(path))

    def load_preset(self, path: str | Path) -> bool:
        """Load a TOML preset; a bad file is refused with its reason (nothing changes)."""
        try:
            config = self._root.load(path)
        except ConfigError as err:
            self._show_error(str(err))
            self.change_log.add("preset refused", str(err), error=True)
            return False
        self.set_config(config, f"preset {Path(path).name}")
        return True

    def _ask_load(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(
            self, "Load parameter preset", "", "TOML presets (*.toml);;All files (*)"
        )
        if path:
            self.load_preset(path)

    def _ask_save(self) -> None:
        path, _ = QtWidgets.QFileDialog.getSaveFileName(
            self, "Save parameter preset", "preset.toml", "TOML presets (*.toml)"
        )
        if path:
            self.save_preset(path)
