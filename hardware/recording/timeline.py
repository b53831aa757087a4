"""A recording's whole timeline: every estimate, control state and event, and the marks on it.

:class:`TimelineScan` reads the small channels of a recording once, in log-time order (the
estimates, the control state, the events; never a depth image), and hands out immutable
:class:`TimelineData` as it goes, so a timeline can draw the part already read while the rest is
being read. :func:`timeline_marks` turns the data into the intervals a timeline marks:

==========  ================================================================================
kind        where
==========  ================================================================================
fault       the session in ``fault`` or ``emergency_stop``, or a watchdog reaction other than
            ``NONE``; an event of level error (a point)
hold        the tick holds the last surface (space ``holding``)
stop        the tick stopped the arm for want of a surface (space ``stopped``)
contact     the margin under :data:`~hapticloud.core.studies.run.CONTACT_M` (5 mm): the
            simulator's true margin where the recording has it, else the loop's ``d_proj``
==========  ================================================================================

No threads and no Qt here: the player (:mod:`.cursor`) runs the scan on a thread of its own.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import format as fmt
from .reader import Recording

FloatArray = NDArray[np.float64]

#: Space states of the control state channel, by code (the order of the tick's).
SPACE_CODES = {"known": 0, "holding": 1, "stopped": 2}
#: Session states that count as a fault on the timeline.
FAULT_STATES = frozenset({"fault", "emergency_stop"})
MARK_KINDS = ("fault", "hold", "stop", "contact")


@dataclass(frozen=True)
class Mark:
    """One marked interval ``[t0, t1]`` (log time, s; ``t0 == t1`` for a point) with its text."""

    kind: str
    t0: float
    t1: float
    text: str = ""


@dataclass(frozen=True)
class CameraLane:
    """One camera's estimates, oldest first: log time, validity, centroid, normal, the HIP it
    was estimated for, and ``d_proj`` (mm; NaN where invalid or without a HIP)."""

    name: str
    t: FloatArray
    valid: NDArray[np.bool_]
    centroid: FloatArray
    normal: FloatArray
    hip: FloatArray
    d_proj_mm: FloatArray

    def newest_at(self, t_s: float) -> int:
        """Index of the newest estimate at or before ``t_s`` (-1: none)."""
        return bisect.bisect_right(self.t, t_s + 1e-12) - 1  # type: ignore[arg-type]


@dataclass(frozen=True)
class ControlLane:
    """The control states, oldest first (100 Hz). ``margin_mm`` is the simulator's true margin
    (NaN where not recorded); ``state`` and ``space`` the session and space states."""

    t: FloatArray
    d_proj_mm: FloatArray
    fused_valid: NDArray[np.bool_]
    margin_mm: FloatArray
    space: NDArray[np.int8]
    tick_us: FloatArray
    misses: FloatArray
    state: tuple[str, ...]


@dataclass(frozen=True)
class Event:
    t: float
    level: str
    source: str
    text: str


@dataclass(frozen=True)
class TimelineData:
    """What the scan has read so far (everything up to ``scanned_s``; ``complete`` at the end)."""

    start_s: float
    end_s: float
    scanned_s: float
    complete: bool
    cameras: tuple[CameraLane, ...]
    control: ControlLane
    events: tuple[Event, ...]
    marks: tuple[Mark, ...] = ()
    error: str = ""

    def covers(self, t_s: float) -> bool:
        """Whether everything at or before ``t_s`` has been read."""
        return self.complete or t_s < self.scanned_s

    def camera(self, name: str) -> CameraLane | None:
        for lane in self.cameras:
            if lane.name == name:
                return lane
        return None


def _empty_control() -> ControlLane:
    z = np.empty(0)
    return ControlLane(z, z, np.empty(0, bool), z, np.empty(0, np.int8), z, z, ())


def empty_timeline(start_s: float, end_s: float, cameras: Sequence[str]) -> TimelineData:
    lanes = tuple(_lane(name, [], [], [], [], []) for name in cameras)
    return TimelineData(start_s, end_s, start_s, False, lanes, _empty_control(), ())


def _vec3(value: Any) -> tuple[float, float, float]:
    try:
        x, y, z = (float(v) if v is not None else math.nan for v in value)
        return x, y, z
    except (TypeError, ValueError):
        return math.nan, math.nan, math.nan


def _num(value: Any) -> float:
    try:
        return float(value) if value is not None else math.nan
    except (TypeError, ValueError):
        return math.nan


def _lane(
    name: str,
    t: list[float],
    valid: list[bool],
    centroid: list[tuple[float, float, float]],
    normal: list[tuple[float, float, float]],
    hip: list[tuple[float, float, float]],
    r_hip_m: float = 0.0,
) -> CameraLane:
    tt = np.asarray(t, dtype=np.float64)
    ok = np.asarray(valid, dtype=bool)
    c = np.asarray(centroid, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normal, dtype=np.float64).reshape(-1, 3)
    h = np.asarray(hip, dtype=np.float64).reshape(-1, 3)
    # d_proj = (c - h) . (-n) - r_hip (core.haptics.d_proj, vectorised)
    d = np.einsum("ij,ij->i", c - h, -n) - r_hip_m if len(tt) else np.empty(0)
    d_mm = np.where(ok, 1e3 * d, np.nan)
    return CameraLane(name, tt, ok, c, n, h, d_mm)


class TimelineScan:
    """Reads the small channels of ``rec`` in log-time order; :meth:`run` calls ``publish``
    with a new :class:`TimelineData` at most every ``every_messages`` messages and at the end.

    ``rec`` is used by this scan only (a :class:`Recording` is not thread-safe: the player opens
    one for it). ``stop()`` returns ``True`` to end the scan early.
    """

    def __init__(self, rec: Recording, r_hip_m: float) -> None:
        self.rec = rec
        self.r_hip_m = r_hip_m
        self.cameras = sorted(rec.cameras_with_estimates() or rec.cameras)
        self._est: dict[str, tuple[list, list, list, list, list]] = {
            c: ([], [], [], [], []) for c in self.cameras
        }
        self._ctl: dict[str, list[Any]] = {
            k: [] for k in ("t", "d", "fv", "m", "sp", "tick", "miss", "state")
        }
        self._events: list[Event] = []
        self._scanned = rec.start_s

    def topics(self) -> list[str]:
        have = set(self.rec.channels)
        wanted = [fmt.estimate_topic(c) for c in self.cameras]
        wanted += [fmt.CONTROL_TOPIC, fmt.EVENTS_TOPIC]
        return [t for t in wanted if t in have]

    def run(
        self,
        publish: Callable[[TimelineData], None],
        stop: Callable[[], bool] = lambda: False,
        every_messages: int = 4000,
    ) -> TimelineData:
        est_topics = {fmt.estimate_topic(c): c for c in self.cameras}
        n = 0
        error = ""
        try:
            for topic, ns, data in self.rec.raw_messages(self.topics()):
                t = ns / 1e9
                body = self.rec.decode(topic, data)
                camera = est_topics.get(topic)
                if camera is not None:
                    self._add_estimate(camera, t, body)
                elif topic == fmt.CONTROL_TOPIC:
                    self._add_control(t, body)
                else:
                    self._add_event(t, body)
                self._scanned = t
                n += 1
                if n % every_messages == 0:
                    if stop():
                        break
                    publish(self.data(complete=False))
        except Exception as err:  # a torn chunk: what was read stands
            error = str(err).splitlines()[0] if str(err) else type(err).__name__
        out = self.data(complete=not stop(), error=error)
        publish(out)
        return out

    def _add_estimate(self, camera: str, t: float, body: dict[str, Any]) -> None:
        ts, valid, cen, nor, hip = self._est[camera]
        ts.append(t)
        valid.append(bool(body.get("valid")))
        cen.append(_vec3(body.get("centroid", (math.nan,) * 3)))
        nor.append(_vec3(body.get("normal", (math.nan,) * 3)))
        h = body.get("hip")
        hip.append(_vec3(h) if h is not None else (math.nan,) * 3)

    def _add_control(self, t: float, body: dict[str, Any]) -> None:
        c = self._ctl
        c["t"].append(t)
        c["d"].append(1e3 * _num(body.get("d_proj_m")))
        c["fv"].append(bool(body.get("fused_valid")))
        c["m"].append(1e3 * _num(body.get("true_margin_m")))
        c["sp"].append(SPACE_CODES.get(str(body.get("space", "")), -1))
        c["tick"].append(_num(body.get("tick_us")))
        c["miss"].append(_num(body.get("misses")))
        c["state"].append(str(body.get("state", "")))

    def _add_event(self, t: float, body: Any) -> None:
        level = {1: "debug", 2: "info", 3: "warning", 4: "error", 5: "fatal"}.get(
            int(getattr(body, "level", 2)), "info"
        )
        self._events.append(
            Event(t, level, str(getattr(body, "name", "")), str(getattr(body, "message", "")))
        )

    def data(self, *, complete: bool, error: str = "") -> TimelineData:
        lanes = tuple(_lane(c, *self._est[c], r_hip_m=self.r_hip_m) for c in self.cameras)
        c = self._ctl
        control = ControlLane(
            np.asarray(c["t"], dtype=np.float64),
            np.asarray(c["d"], dtype=np.float64),
            np.asarray(c["fv"], dtype=bool),
            np.asarray(c["m"], dtype=np.float64),
            np.asarray(c["sp"], dtype=np.int8),
            np.asarray(c["tick"], dtype=np.float64),
            np.asarray(c["miss"], dtype=np.float64),
            tuple(c["state"]),
        )
        events = tuple(self._events)
        scanned = self.rec.end_s if complete else self._scanned
        rec = self.rec
        partial = TimelineData(
            rec.start_s, rec.end_s, scanned, complete, lanes, control, events, error=error
        )
        return TimelineData(
            rec.start_s,
            rec.end_s,
            scanned,
            complete,
            lanes,
            control,
            events,
            tuple(timeline_marks(partial)),
            error,
        )


# ----- marks --------------------------------------------------------------------------------------
def intervals(t: FloatArray, on: NDArray[np.bool_], end_s: float | None = None) -> list[tuple]:
    """``[(t0, t1), ...]`` where ``on`` holds, each from its first sample to the first sample
    after it (or its last sample, or ``end_s``, at the end)."""
    on = np.asarray(on, dtype=bool)
    if not len(on):
        return []
    edges = np.flatnonzero(np.diff(np.concatenate(([False], on, [False])).astype(np.int8)))
    out = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        t1 = t[b] if b < len(t) else (t[-1] if end_s is None else max(t[-1], end_s))
        out.append((float(t[a]), float(t1)))
    return out


def timeline_marks(data: TimelineData, contact_m: float | None = None) -> list[Mark]:
    """The marks of ``data`` (see the module docstring), by time."""
    if contact_m is None:
        from hapticloud.core.studies.run import CONTACT_M

        contact_m = CONTACT_M
    ctl = data.control
    marks: list[Mark] = []
    if len(ctl.t):
        states = np.array(ctl.state, dtype=object)
        fault = np.isin(states, list(FAULT_STATES))
        for t0, t1 in intervals(ctl.t, fault):
            i = bisect.bisect_left(ctl.t, t0)  # type: ignore[arg-type]
            marks.append(Mark("fault", t0, t1, f"session {states[i]}"))
        for code, kind in ((1, "hold"), (2, "stop")):
            for t0, t1 in intervals(ctl.t, ctl.space == code):
                marks.append(Mark(kind, t0, t1, f"space {kind}"))
        margin = ctl.margin_mm if np.isfinite(ctl.margin_mm).any() else ctl.d_proj_mm
        what = "true margin" if margin is ctl.margin_mm else "d_proj"
        with np.errstate(invalid="ignore"):
            contact = np.isfinite(margin) & (margin < 1e3 * contact_m)
        for t0, t1 in intervals(ctl.t, contact):
            sel = (ctl.t >= t0) & (ctl.t <= t1)
            low = float(np.nanmin(margin[sel])) if sel.any() else math.nan
            marks.append(Mark("contact", t0, t1, f"contact: min {what} {low:+.1f} mm"))
    for ev in data.events:
        kind = event_kind(ev)
        if kind is not None:
            marks.append(Mark(kind, ev.t, ev.t, f"{ev.source}: {ev.text}"))
    marks.sort(key=lambda m: (m.t0, m.kind))
    return marks


def event_kind(ev: Event) -> str | None:
    """The mark of an event: ``fault`` for a watchdog reaction that damps or cuts torque, a
    session fault or e-stop, an error, an e-stop key; ``hold`` for a reaction that holds the
    surface; ``None`` for the rest (space changes are marked from the control state)."""
    head = ev.text.split(":", 1)[0].strip().lower()
    if ev.level in ("error", "fatal") or ev.source == "estop":
        return "fault"
    if ev.source == "reaction":
        level = ev.text.replace(":", " ").split(" ", 1)[0].upper()  # "NONE : ...", "DAMPING x: ..."
        if level in ("NONE", ""):
            return None
        return "hold" if level == "HOLD_SURFACE" else "fault"
    if ev.source == "state" and head in FAULT_STATES:
        return "fault"
    return None


def merge_marks(marks: Iterable[Mark], min_gap_s: float) -> list[Mark]:
    """Marks of one kind closer than ``min_gap_s`` merged (what a strip of a few hundred pixels
    can show of a long recording)."""
    out: list[Mark] = []
    last: dict[str, int] = {}
    for m in sorted(marks, key=lambda m: m.t0):
        i = last.get(m.kind)
        if i is not None and m.t0 - out[i].t1 <= min_gap_s:
            prev = out[i]
            out[i] = Mark(m.kind, prev.t0, max(prev.t1, m.t1), prev.text)
            continue
        last[m.kind] = len(out)
        out.append(m)
    return out


__all__ = [
    "FAULT_STATES",
    "MARK_KINDS",
    "SPACE_CODES",
    "CameraLane",
    "ControlLane",
    "Event",
    "Mark",
    "TimelineData",
    "TimelineScan",
    "empty_timeline",
    "event_kind",
    "intervals",
    "merge_marks",
    "timeline_marks",
]
