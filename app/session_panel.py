"""The session panel: the control process's state, commands, telemetry and alarms.

Fed by the window's timer with the newest :class:`~hapticloud.hardware.control.ControlSnapshot`
(:meth:`SessionPanel.show_control`, text refreshed at most every :data:`REFRESH_S`) and the
session's alarms. The buttons call the :class:`~hapticloud.hardware.live.session.Session` (one
pipe write each); the e-stop button calls the window's emergency stop (perception and drives).
"""

from __future__ import annotations

import math
import time
from typing import Any

from hapticloud.hardware.live.contract import SessionPhase
from hapticloud.hardware.live.session import Session
from hapticloud.hardware.session.states import state_label
from PyQt6 import QtCore, QtGui, QtWidgets

from .status import TIMES

NO_VALUE = "\u2013"
REFRESH_S = 0.2

#: Background / foreground per session state (and the app-side phases).
STATE_STYLE = {
    "starting": "background:#fff3cd; color:#7a5b00;",
    "disconnected": "background:#e0e0e0; color:#333333;",
    "connected": "background:#d6e4f0; color:#1b3a57;",
    "ready": "background:#d6e4f0; color:#1b3a57; font-weight:700;",
    "enabled": "background:#d4edda; color:#155724; font-weight:700;",
    "fault": "background:#f8d7da; color:#721c24; font-weight:700;",
    "emergency_stop": "background:#c0392b; color:white; font-weight:700;",
    "failed": "background:#6f1d1b; color:white; font-weight:700;",
    "closed": "background:#e0e0e0; color:#333333;",
}
REACTION_COLOURS = {
    "NONE": "#155724",
    "HOLD_SURFACE": "#7a5b00",
    "DAMPING": "#b35900",
    "TORQUE_OFF": "#b00020",
}
ALARM_COLOURS = {
    "state": "#1b3a57",
    "reaction": "#b35900",
    "space": "#7a5b00",
    "app": "#6f1d1b",
}
#: Below this simulated-per-wall time, the panel says the simulation is behind real time.
SIM_BEHIND_FACTOR = 0.95
SPACE_COLOURS = {"known": "#1b5e20", "holding": "#7a5b00", "stopped": "#b35900"}

#: The figures shown, in order: key -> (label, tool tip).
FIELDS = {
    "reaction": ("reaction", "watchdog reaction level, its source and reason"),
    "space": (
        "space",
        "what the tick knows around the HIP: known (a fresh surface or proven free space), "
        "holding (the last surface held and grown) or stopped (position held), and why",
    ),
    "rate": (
        "control rate",
        "ticks per second of the loop (target 800 Hz); with simulated drives, the simulation's "
        "speed against real time (it slows down when the machine cannot keep up)",
    ),
    "misses": ("misses", "ticks that missed their 1250 µs deadline since start"),
    "tick": ("tick", "time of the newest tick / the longest since the previous snapshot"),
    "bus": ("bus load", "CAN FD bus occupancy between the last two snapshots"),
    "estimate": ("estimate", "age of the newest estimate the loop's fusion admitted"),
    "cameras": ("camera ages", "time since each camera's newest frame reached the loop"),
    "margin": (
        "min margin (fused)",
        "smallest d_proj while enabled and the surface known (HIP surface to fused surface, "
        "not to the true one: the run's truth line says how near it really came; a held "
        "surface, grown toward the HIP while the cameras are late, does not count)",
    ),
    "force": ("force", "force at the HIP beyond transparency (|F|)"),
    "dropped": ("dropped", "snapshots the loop could not write (pipe full) / lost"),
}


def _num(value: float, fmt: str, unit: str) -> str:
    return f"{value:{fmt}} {unit}" if math.isfinite(value) else NO_VALUE


class SessionPanel(QtWidgets.QWidget):
    """State, enable / disable / reset / e-stop, figures with units, alarms (newest on top)."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.session: Session | None = None
        self._estop: Any = None
        self._last = 0.0
        self._alarm_count = 0
        self._newest_alarm: Any = None

        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(4, 4, 4, 4)
        layout.setSpacing(4)
        self.state_label = QtWidgets.QLabel(" NO SESSION ", self)
        self.state_label.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.state_label.setMinimumHeight(26)
        self.state_label.setStyleSheet(STATE_STYLE["closed"] + "font-size:13px;")
        layout.addWidget(self.state_label)

        buttons = QtWidgets.QHBoxLayout()
        buttons.setSpacing(3)
        self.enable_button = QtWidgets.QPushButton("Enable", self)
        self.disable_button = QtWidgets.QPushButton("Disable", self)
        self.reset_button = QtWidgets.QPushButton("Reset", self)
        self.estop_button = QtWidgets.QPushButton("E-STOP", self)
        self.enable_button.setToolTip("drives to OPERATION ENABLED: the haptic torques are sent")
        self.disable_button.setToolTip("drives disabled, zero torque")
        self.reset_button.setToolTip(
            "clear a fault or an emergency stop (refused while its cause is active)"
        )
        self.estop_button.setToolTip("emergency stop: drives quick stop, perception stopped (Esc)")
        self.estop_button.setStyleSheet(
            "QPushButton { background:#c0392b; color:white; font-weight:700; }"
        )
        for button in (
            self.enable_button,
            self.disable_button,
            self.reset_button,
            self.estop_button,
        ):
            # No focus: Space must stay the e-stop, not "click the focused button".
            button.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
            buttons.addWidget(button)
        self.enable_button.clicked.connect(lambda: self._do("enable"))
        self.disable_button.clicked.connect(lambda: self._do("disable"))
        self.reset_button.clicked.connect(lambda: self._do("reset"))
        self.estop_button.clicked.connect(self._estop_clicked)
        layout.addLayout(buttons)

        # Two columns of (name, value): the dock shares its height with the parameters.
        grid = QtWidgets.QGridLayout()
        grid.setContentsMargins(2, 0, 2, 0)
        grid.setVerticalSpacing(1)
        grid.setHorizontalSpacing(6)
        self.values: dict[str, QtWidgets.QLabel] = {}
        small = 0
        for key, (label, tip) in FIELDS.items():
            name = QtWidgets.QLabel(label, self)
            value = QtWidgets.QLabel(NO_VALUE, self)
            value.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.NoTextInteraction)
            name.setStyleSheet("color:#555555;")
            name.setToolTip(tip)
            value.setToolTip(tip)
            if key in ("reaction", "space", "cameras", "dropped"):  # long: a full row
                row = {"reaction": 0, "space": 1}.get(key, 10 + len(self.values))
                value.setWordWrap(True)
                grid.addWidget(name, row, 0)
                grid.addWidget(value, row, 1, 1, 3)
            else:
                row, col = 2 + small // 2, 2 * (small % 2)
                grid.addWidget(name, row, col)
                grid.addWidget(value, row, col + 1)
                small += 1
            self.values[key] = value
        grid.setColumnStretch(1, 1)
        grid.setColumnStretch(3, 1)
        layout.addLayout(grid)

        self.alarms = QtWidgets.QTreeWidget(self)
        self.alarms.setHeaderLabels(("time", "kind", "alarm"))
        self.alarms.setRootIsDecorated(False)
        self.alarms.setUniformRowHeights(True)
        self.alarms.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)
        self.alarms.setColumnWidth(0, 92)
        self.alarms.setColumnWidth(1, 58)
        self.alarms.setToolTip("session transitions and watchdog reactions, newest on top")
        layout.addWidget(QtWidgets.QLabel("alarms (newest on top)", self))
        layout.addWidget(self.alarms, 1)
        self._buttons_for(None)

    # ----- wiring -------------------------------------------------------------------------------
    def set_session(self, session: Session | None, estop: Any) -> None:
        """Show ``session``; ``estop(reason)`` is the window's emergency stop."""
        self.session = session
        self._estop = estop
        self._newest_alarm = None
        self.alarms.clear()
        self.refresh(force=True)

    def _do(self, command: str) -> None:
        if self.session is not None:
            getattr(self.session, command)()

    def _estop_clicked(self) -> None:
        if self._estop is not None:
            self._estop("emergency stop (session panel)")
        elif self.session is not None:
            self.session.emergency_stop("emergency stop (session panel)")

    def _buttons_for(self, state: str | None) -> None:
        running = self.session is not None and self.session.running
        self.enable_button.setEnabled(running and state == "ready")
        self.disable_button.setEnabled(running and state == "enabled")
        self.reset_button.setEnabled(running and state in ("fault", "emergency_stop"))
        self.estop_button.setEnabled(running or self.session is not None)

    # ----- display ------------------------------------------------------------------------------
    def state_text(self) -> str:
        """The state shown (``enabled``, ``emergency_stop``, ``starting``, ``failed``...)."""
        session = self.session
        if session is None:
            return "none"
        if session.phase is not SessionPhase.RUNNING:
            return session.phase.value
        snap = session.latest
        return snap.state if snap is not None else "starting"

    def refresh(self, *, force: bool = False) -> None:
        """Update from the session's newest snapshot (numbers at most every :data:`REFRESH_S`)."""
        session = self.session
        state = self.state_text()
        text = f" {state_label(state)} "
        if self.state_label.text() != text:
            self.state_label.setText(text)
            self.state_label.setStyleSheet(
                STATE_STYLE.get(state, STATE_STYLE["closed"]) + "font-size:13px;"
            )
            tip = session.message if session is not None and session.message else state
            self.state_label.setToolTip(tip)
            self._buttons_for(state)
        now = time.monotonic()
        if not force and now - self._last < REFRESH_S:
            return
        self._last = now
        self._show_alarms()
        snap = session.latest if session is not None else None
        if snap is None:
            why = session.message if session is not None else "no control process"
            self.values["reaction"].setText(why or NO_VALUE)
            return
        colour = REACTION_COLOURS.get(snap.reaction, "#333333")
        source = f" ({snap.reaction_source})" if snap.reaction_source else ""
        self.values["reaction"].setText(
            f"<span style='color:{colour}; font-weight:600'>{snap.reaction}</span>{source}: "
            f"{snap.reaction_reason}"
        )
        v = self.values
        colour = SPACE_COLOURS.get(snap.space, "#333333")
        why = f": {snap.space_reason}" if snap.space_reason else ""
        v["space"].setText(
            f"<span style='color:{colour}; font-weight:600'>{snap.space.upper()}</span>{why}"
        )
        rate = _num(snap.control_rate_hz, ".1f", "Hz")
        factor = getattr(snap, "sim_time_factor", math.nan)
        if math.isfinite(factor):
            # The simulated drives run on the loop's clock: a slow machine slows the simulation.
            behind = factor < SIM_BEHIND_FACTOR
            colour = "#b35900" if behind else "#1b5e20"
            note = "simulation behind real time" if behind else "simulated"
            rate += f" <span style='color:{colour}'>({note}: {factor:.2f}{TIMES} real time)</span>"
        v["rate"].setText(rate)
        ticks = max(snap.tick, 1)
        v["misses"].setText(f"{snap.misses} ({1e4 * snap.misses / ticks:.1f}/10k)")
        tick, worst = _num(snap.tick_us, ".0f", "µs"), _num(snap.tick_us_max, ".0f", "µs")
        v["tick"].setText(f"{tick} / max {worst}")
        v["bus"].setText(_num(100.0 * snap.bus_load, ".1f", "%"))
        v["estimate"].setText(_num(1e3 * snap.estimate_age_s, ".0f", "ms"))
        cams = "  ".join(f"{n} {_num(1e3 * age, '.0f', 'ms')}" for n, age in snap.camera_age_s)
        v["cameras"].setText(cams or NO_VALUE)
        v["margin"].setText(_num(1e3 * snap.min_d_proj_m, ".1f", "mm"))
        force = math.sqrt(sum(f * f for f in snap.force_n))
        v["force"].setText(_num(force, ".2f", "N"))
        lost = session.lost if session is not None else 0
        v["dropped"].setText(f"{snap.dropped_snapshots} snapshots by the loop, {lost} lost")

    def _show_alarms(self) -> None:
        session = self.session
        if session is None or not session.alarms:
            return
        newest = session.alarms[0]
        if newest is self._newest_alarm:
            return
        fresh = []
        for alarm in session.alarms:  # newest first
            if alarm is self._newest_alarm:
                break
            fresh.append(alarm)
        self._newest_alarm = newest
        for alarm in reversed(fresh):  # insert oldest first: the newest ends on top
            item = QtWidgets.QTreeWidgetItem((alarm.clock(), alarm.kind, alarm.text))
            item.setToolTip(2, alarm.text)
            brush = QtGui.QBrush(QtGui.QColor(ALARM_COLOURS.get(alarm.kind, "#333333")))
            for col in range(3):
                item.setForeground(col, brush)
            self.alarms.insertTopLevelItem(0, item)
        while self.alarms.topLevelItemCount() > session.alarms.maxlen:
            self.alarms.takeTopLevelItem(self.alarms.topLevelItemCount() - 1)
