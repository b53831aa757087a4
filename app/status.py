"""The status bar: the system's health at a glance, every number with its unit.

Fields: source state, session state (the control process), control rate and deadline misses,
each camera's measured rate, simulation speed, perception latency (median
and worst of the last second), estimate age, frame-to-screen latency, error against the truth and
the view's own update rate. Text is refreshed a few times a second (numbers changing at 30 Hz
cannot be read) from the newest snapshot the window already holds; nothing is computed here
beyond medians of the history the snapshot carries.
"""

from __future__ import annotations

import math
import time

import numpy as np
from hapticloud.hardware.live.contract import Snapshot, SourceState
from hapticloud.hardware.session.states import state_label
from PyQt6 import QtWidgets

NO_VALUE = "\u2013"  # en dash: no value yet
TIMES = "\u00d7"
REFRESH_S = 0.25  # status text refresh period
WINDOW_S = 1.0  # statistics over the last second of frames

_STATE_STYLE = {
    SourceState.STARTING: "background:#fff3cd; color:#7a5b00;",
    SourceState.RUNNING: "background:#d4edda; color:#155724;",
    SourceState.STOPPED: "background:#c0392b; color:white; font-weight:700;",
    SourceState.FAILED: "background:#6f1d1b; color:white; font-weight:700;",
}


def _ms(value: float, digits: int = 1) -> str:
    return NO_VALUE if not math.isfinite(value) else f"{value:.{digits}f} ms"


def _mm(value: float) -> str:
    return NO_VALUE if not math.isfinite(value) else f"{value:.1f} mm"


class StatusPanel:
    """Labels in a :class:`QStatusBar`; :meth:`show` updates them (rate-limited)."""

    FIELDS = (
        "state",
        "session",
        "control",
        "cameras",
        "speed",
        "perception",
        "age",
        "latency",
        "error",
        "fusion",
        "view",
    )

    def __init__(self, bar: QtWidgets.QStatusBar) -> None:
        self.bar = bar
        self.labels: dict[str, QtWidgets.QLabel] = {}
        for key in self.FIELDS:
            label = QtWidgets.QLabel(NO_VALUE, bar)
            label.setContentsMargins(4, 0, 4, 0)
            bar.addPermanentWidget(label)
            self.labels[key] = label
        self.labels["state"].setMinimumWidth(84)
        self._last = 0.0
        self._plant_factor = math.nan  # the session's simulation clock (NaN: no session)
        self.set_state(SourceState.STARTING, "")
        self._tips()

    def _tips(self) -> None:
        tips = {
            "cameras": "frames per second each camera delivered (wall clock, last second)",
            "speed": "simulation time per wall time: with a session the control process's "
            "simulated drives and arm (below 1: the machine cannot keep up and the simulation "
            "runs slower), else the cameras' clock (a frame not rendered in time is dropped)",
            "perception": "perception time per frame, stages A-E: median / worst of the last "
            "second",
            "age": "age of the newest valid camera estimate at the newest frame (source clock): "
            "grows while the cameras see no surface",
            "latency": "frame-to-screen: from the camera frame's capture to this display",
            "error": "distance from the fused centroid to the true closest point (simulation)",
            "fusion": "whether the cameras agree: how far apart their own surfaces lie along the "
            "HIP's distance; DISAGREE when more than their scatter explains (the nearer camera "
            "answers); 'crease': cameras that saw two surfaces and took the nearer",
            "view": "3D view updates per second",
            "session": "state of the control process's session (drives)",
            "control": "control loop rate / deadline misses since it started",
        }
        for key, tip in tips.items():
            self.labels[key].setToolTip(tip)

    def show_session(self, state: str, snap: object | None, style: str) -> None:
        """The session's state (coloured like the session panel), control rate and misses."""
        label = self.labels["session"]
        text = f" {state_label(state)} "
        if label.text() != text:
            label.setText(text)
            label.setStyleSheet(style)
        if snap is None:
            self.labels["control"].setText(f"control {NO_VALUE}")
            self._plant_factor = math.nan
            return
        self._plant_factor = getattr(snap, "sim_time_factor", math.nan)
        rate = getattr(snap, "control_rate_hz", math.nan)
        misses = getattr(snap, "misses", 0)
        rate_text = f"{rate:.0f} Hz" if math.isfinite(rate) else NO_VALUE
        self.labels["control"].setText(f"control {rate_text}, {misses} misses")

    def _show_fusion(self, snap: Snapshot) -> None:
        """The cameras' agreement (the fused quality) and what each camera's estimate noted."""
        label, fused = self.labels["fusion"], snap.fused
        notes = [
            f"{cam.name}: {cam.estimate.note}"
            for cam in snap.cameras
            if cam.estimate.valid and getattr(cam.estimate, "note", "")
        ]
        if fused is None or not fused.valid:
            text, style, tip = f"agree {NO_VALUE}", "", "no fused surface"
        elif fused.disagree:
            text = f"DISAGREE {1e3 * fused.disagreement_m:.1f} mm"
            style, tip = "color:#b35900; font-weight:600;", fused.quality_note
        elif len(fused.cameras) < 2:
            text, style, tip = "1 camera", "", fused.quality_note or "one camera in the window"
        else:
            text = f"agree {1e3 * fused.disagreement_m:.1f} mm"
            style, tip = "", fused.quality_note
        two = sum(getattr(cam.estimate, "surfaces", 1) > 1 for cam in snap.cameras)
        if two:
            text += f", {two} crease"  # cameras that saw two surfaces (the nearer taken)
        label.setText(text)
        label.setStyleSheet(style)
        label.setToolTip("\n".join([tip, *notes]))

    def set_state(self, state: SourceState, message: str) -> None:
        label = self.labels["state"]
        label.setText(f" {state.value.upper()} ")
        label.setStyleSheet(_STATE_STYLE[state])
        label.setToolTip(message or state.value)

    def show(
        self,
        snap: Snapshot,
        view_fps: float,
        *,
        state: SourceState | None = None,
        force: bool = False,
    ) -> None:
        """Refresh from ``snap``: the state at once, the numbers at most every
        :data:`REFRESH_S` (unless ``force``). ``state`` overrides the snapshot's (a stop the
        window requested is shown before the source confirms it)."""
        state = snap.state if state is None else state
        if self.labels["state"].text().strip() != state.value.upper():
            self.set_state(state, snap.message)
        now = time.monotonic()
        if not force and now - self._last < REFRESH_S:
            return
        self._last = now
        rates = "  ".join(
            f"{cam.name} {cam.rate_hz:4.1f} Hz"
            if math.isfinite(cam.rate_hz)
            else f"{cam.name} {NO_VALUE}"
            for cam in snap.cameras
        )
        self.labels["cameras"].setText(rates or "no camera")
        rtf = self._plant_factor
        if not math.isfinite(rtf):
            rtf = snap.real_time_factor
        self.labels["speed"].setText(
            f"sim {rtf:.2f}{TIMES}" if math.isfinite(rtf) else f"sim {NO_VALUE}"
        )
        frames = snap.history.frames
        recent = frames[snap.history.frame("t") > snap.t - WINDOW_S] if len(frames) else frames
        if len(recent):
            total = recent[:, -1]
            total = total[np.isfinite(total)]
            self.labels["perception"].setText(
                f"perception {_ms(float(np.median(total)))} / {_ms(float(total.max()))}"
                if len(total)
                else f"perception {NO_VALUE}"
            )
        fused = snap.fused
        valid_t = [c.estimate.t for c in snap.cameras if c.estimate.valid]
        age = 1e3 * (snap.t - max(valid_t)) if valid_t else math.inf
        self.labels["age"].setText(
            f"age {_ms(age, 0)}" if math.isfinite(age) else "no valid estimate"
        )
        self.labels["latency"].setText(f"to screen {_ms(1e3 * (now - snap.captured), 0)}")
        err = math.nan
        if snap.truth is not None and fused is not None and fused.valid:
            err = 1e3 * float(np.linalg.norm(fused.centroid - snap.truth.point))
        self.labels["error"].setText(f"error {_mm(err)}")
        self._show_fusion(snap)
        self.labels["view"].setText(
            f"view {view_fps:4.1f} fps" if math.isfinite(view_fps) else f"view {NO_VALUE}"
        )
