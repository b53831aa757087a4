"""``hapticloud app --report FILE``: what the window showed, as figures, written at exit.

The window hands every snapshot it shows (and the session's newest control snapshot) to
:class:`AppReport`; at exit it writes one JSON object:

- ``session``: ``states`` as ``[[t_s, state], ...]`` (t from the window's start), ``faults``,
  ``space`` changes (known / holding / stopped, with reasons), ``misses_per_10k``;
- ``cameras.<name>.rate_hz_median``; ``sim.real_time_factor_median``: simulated time per wall
  time of the simulation's clock (``sim.clock``): with a session the control process's (the
  simulated drives and arm), else the cameras' (which drop frames rather than slow down);
- ``fused_error_mm.median`` / ``.p90``: the fused surface's centroid against the simulator's
  true closest point, over the snapshots with a valid fused surface;
- ``view.fps_median``; ``view.frame_to_screen_ms_median`` (camera exposure to the paint);
- ``truth`` and ``verdict``: the HIP's true margin at each shown snapshot (sampled at the display
  rate, so a brief dip between two paints can be missed) judged like every run (SAFE/UNSAFE).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from hapticloud.core.studies.stats import json_float, summary
from hapticloud.core.studies.verdict import judge


class AppReport:
    """Collects what the window shows; :meth:`write` turns it into the report."""

    def __init__(self, r_hip_m: float) -> None:
        self.r_hip_m = r_hip_m
        self.t0 = time.monotonic()
        self.states: list[list[Any]] = []
        self.faults: list[list[Any]] = []
        self.space: list[list[Any]] = []
        self.rates: dict[str, list[float]] = {}
        self.rtf: list[float] = []
        self.plant_rtf: list[float] = []
        self.fused_error_mm: list[float] = []
        self.fps: list[float] = []
        self.to_screen_ms: list[float] = []
        self.truth_t: list[float] = []
        self.margin_m: list[float] = []
        self.misses_per_10k = math.nan
        self._newest_alarm: Any = None

    def _t(self, monotonic: float) -> float:
        return round(monotonic - self.t0, 4)

    def observe_frame(self, snap: Any, view_fps: float, now: float) -> None:
        """One snapshot the 3D view shows now
        (:class:`~hapticloud.hardware.live.contract.Snapshot`)."""
        for cam in snap.cameras:
            if math.isfinite(cam.rate_hz):
                self.rates.setdefault(cam.name, []).append(cam.rate_hz)
        if math.isfinite(snap.real_time_factor):
            self.rtf.append(snap.real_time_factor)
        if math.isfinite(view_fps):
            self.fps.append(view_fps)
        self.to_screen_ms.append(1e3 * (now - snap.captured))
        truth, fused = snap.truth, snap.fused
        if truth is None:
            return
        self.truth_t.append(self._t(now))
        self.margin_m.append(float(truth.distance_m) - self.r_hip_m)
        if fused is not None and fused.valid:
            self.fused_error_mm.append(1e3 * float(np.linalg.norm(fused.centroid - truth.point)))

    def observe_session(self, state: str, session: Any) -> None:
        """The session's state as shown, its new alarms and its newest control snapshot."""
        now = self._t(time.monotonic())
        if not self.states or self.states[-1][1] != state:
            self.states.append([now, state])
        fresh = []
        for alarm in session.alarms:  # newest first
            if alarm is self._newest_alarm:
                break
            fresh.append(alarm)
        if fresh:
            self._newest_alarm = fresh[0]
        for alarm in reversed(fresh):
            entry = [self._t(alarm.t), alarm.text]
            if alarm.kind == "space":
                self.space.append(entry)
            elif (alarm.kind == "reaction" and alarm.text.startswith("TORQUE_OFF")) or (
                alarm.kind == "state" and alarm.text.startswith("fault")
            ):
                self.faults.append(entry)
        control = session.latest
        if control is not None:
            self.misses_per_10k = 1e4 * control.misses / max(int(control.tick), 1)
            factor = getattr(control, "sim_time_factor", math.nan)
            if math.isfinite(factor):
                self.plant_rtf.append(factor)

    def to_json(self) -> dict[str, Any]:
        t = np.array(self.truth_t, dtype=np.float64)
        verdict = judge(t, np.array(self.margin_m, dtype=np.float64))
        return {
            "duration_s": json_float(time.monotonic() - self.t0),
            "session": {
                "states": self.states,
                "faults": self.faults,
                "space": self.space,
                "misses_per_10k": json_float(self.misses_per_10k),
            },
            "cameras": {
                name: {"rate_hz_median": _median(v)} for name, v in sorted(self.rates.items())
            },
            "sim": {
                "real_time_factor_median": _median(self.plant_rtf or self.rtf),
                "clock": "control process" if self.plant_rtf else "cameras",
                "cameras_real_time_factor_median": _median(self.rtf),
            },
            "fused_error_mm": summary(np.array(self.fused_error_mm)),
            "view": {
                "fps_median": _median(self.fps),
                "frame_to_screen_ms_median": _median(self.to_screen_ms),
            },
            "truth": verdict.to_json(),
            "verdict": verdict.label,
        }

    def write(self, path: str | Path) -> Path:
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(self.to_json(), indent=2))
        return out


def _median(values: list[float]) -> float | None:
    return json_float(float(np.median(values))) if values else None


__all__ = ["AppReport"]
