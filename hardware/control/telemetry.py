"""What the control process records and publishes: the per-tick log and the snapshots.

- :class:`TickLog`: one row per tick (the first ``log_ticks``) of times, costs, state, reaction,
  distance, approach speed, torques sent and HIP, returned by
  :meth:`~.process.ControlProcess.stop` as named arrays (:data:`LOG_FIELDS`), so that tests
  assert reactions from the log instead of sleeping.
- :class:`Publisher`: a :class:`~.messages.ControlSnapshot` every ``snapshot_every`` ticks, with
  the session transitions, watchdog reactions and space changes no snapshot carried yet, written
  only when the pipe is writable and the period has time left (:mod:`.slack`).
"""

from __future__ import annotations

import math
import select
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from .messages import ControlSnapshot
from .slack import Slack

__all__ = ["LOG_FIELDS", "Publisher", "TickLog", "constraint_force"]

#: The log's per-tick fields, in the order :meth:`TickLog.arrays` returns them.
LOG_FIELDS = (
    "t",
    "k",
    "lateness_us",
    "tick_us",
    "master_us",
    "control_us",
    "emulator_us",
    "state",
    "reaction",
    "any_fault",
    "complete",
    "d_proj_m",
    "approach_mps",
    "approach_limit_mps",
    "poll_us",
    "inputs_us",
    "send_us",
    "publish_us",
    "fusion_us",
    "body_us",
    "ahead_us",
    "ahead_frames",
    "space",
)
# The columns as the tick writes them: those known when the command is out, then the three of
# the work after it (publishing, fusion, the whole body).
_WRITTEN_AFTER_SEND = ("publish_us", "fusion_us", "body_us")
_COLUMNS = (
    *(name for name in LOG_FIELDS if name not in _WRITTEN_AFTER_SEND),
    *_WRITTEN_AFTER_SEND,
)
_AFTER_SEND = _COLUMNS.index("publish_us")
_MAX_EVENTS_PER_SNAPSHOT = 8
#: Ticks in a row a snapshot may wait for time left in the period (:mod:`.slack`).
MAX_DEFER_TICKS = 8
#: Events kept for the snapshots while none gets out (a reader that stopped reading).
MAX_PENDING_EVENTS = 256


class TickLog:
    """The first ``capacity`` ticks, one row each (all pages touched at construction)."""

    def __init__(self, capacity: int, n_drives: int) -> None:
        self.capacity = int(capacity)
        # Filled, not just zeroed: every page is touched now, not on the first write in the loop.
        self._rows = np.full((self.capacity, len(_COLUMNS)), 0.0)
        self._tau = np.full((self.capacity, n_drives), 0.0)
        self._hip = np.full((self.capacity, 3), 0.0)

    def record(
        self,
        i: int,
        t: float,
        k: int,
        lateness_us: float,
        times: tuple[float, float, float, float],
        tick: Any,
        state_code: int,
        fb: Any,
        ahead: list[Any],
        sent: np.ndarray,
        hip: np.ndarray,
    ) -> None:
        """Tick ``i`` up to its command (``times``: ``perf_counter`` at its start, after the
        feedback poll, after the send, after the stepped drives); ignored past the capacity."""
        if i >= self.capacity:
            return
        p0, p_poll, p3, p4 = times
        p1, p2 = tick.control_started, tick.control_ended
        res = tick.result
        lim = tick.loop.approach_limit_mps
        # One row write: a tenth of the cost of a write per field.
        self._rows[i, :_AFTER_SEND] = (
            t,
            k,
            lateness_us,
            (p4 - p0) * 1e6,
            (p4 - p0 - (p2 - p1) - (p4 - p3)) * 1e6,
            (p2 - p1) * 1e6,
            (p4 - p3) * 1e6,
            state_code,
            int(tick.level),
            fb.any_fault_bit,
            fb.complete,
            tick.d_now,
            res.approach_mps,
            math.nan if lim is None else lim,
            (p_poll - p0) * 1e6,
            (p1 - p_poll) * 1e6,
            (p3 - p2) * 1e6,
            ahead[0],
            ahead[1],
            res.space,
        )
        self._tau[i] = sent
        self._hip[i] = hip

    def finish(self, i: int, p0: float, p4: float, p5: float, p_end: float) -> None:
        """Tick ``i``'s work after its command: publishing (``p4``-``p5``), fusion (to
        ``p_end``) and the whole body from ``p0``: what the deadline sees."""
        if i < self.capacity:
            self._rows[i, _AFTER_SEND:] = ((p5 - p4) * 1e6, (p_end - p5) * 1e6, (p_end - p0) * 1e6)

    def arrays(self, ticks: int) -> dict[str, np.ndarray]:
        """The first ``ticks`` rows as named arrays (:data:`LOG_FIELDS`, ``tau_sent``,
        ``hip_m``)."""
        m = min(ticks, self.capacity)
        out = {f: self._rows[:m, _COLUMNS.index(f)].copy() for f in LOG_FIELDS}
        return out | {"tau_sent": self._tau[:m].copy(), "hip_m": self._hip[:m].copy()}


def _writable(fd: int) -> bool:
    try:
        return bool(select.select((), (fd,), (), 0.0)[1])
    except (OSError, ValueError):
        return False


class Publisher:
    """The snapshots of one control process, and the events they carry.

    ``simulated``: the drives run on a simulated clock (each snapshot then says how fast the
    simulation runs against the wall clock).
    """

    def __init__(
        self, out_conn: Any, tick: Any, every: int, period_s: float, simulated: bool
    ) -> None:
        self._out = out_conn
        self._fd = out_conn.fileno()
        self._tick = tick
        self._every = int(every)
        self._period = float(period_s)
        self._simulated = bool(simulated)
        self.slack = Slack(MAX_DEFER_TICKS)
        self.due = False
        self.seq = 0
        self.dropped = 0
        self.events_dropped = 0
        self.tick_us = 0.0
        """The current tick's cost (µs): :meth:`record_tick`."""
        self.tick_max = 0.0
        self._last: list[Any] = [None, None, None]  # newest transition, reaction, space change
        self._last_fb: Any = None
        self._rate_t = -math.inf
        self._rate_i = 0
        self._rate = 0.0

    def start(self, t: float) -> None:
        """The loop starts at ``t``: the control rate is measured from here."""
        self._rate_t = t

    def collect_events(self) -> None:
        """Session transitions, reactions and space changes since the last collection, into
        the tick's pending events."""
        tick = self._tick
        pending, last = tick.pending_events, self._last
        last[0] = _collect(tick.machine.log, last[0], pending, "state", _state_text)
        last[1] = _collect(tick.watchdogs.log, last[1], pending, "reaction", _reaction_text)
        last[2] = _collect(tick.loop.guard.transitions, last[2], pending, "space", _space_text)

    def maybe_publish(
        self, i: int, t: float, next_deadline: float, fb: Any, sent: Any, hip: Any, misses: int
    ) -> None:
        """Publish tick ``i``'s snapshot if one is due and the time left until
        ``next_deadline`` (``perf_counter``) fits it, else put it off (:mod:`.slack`)."""
        if i % self._every == 0:
            self.due = True
        if not (self.due and self.slack.fits(next_deadline - time.perf_counter())):
            return
        self.due = False
        s0 = time.perf_counter()
        self.collect_events()
        if _writable(self._fd):
            self._send(i, t, fb, sent, hip, misses)
        else:
            self.dropped += 1
        pending = self._tick.pending_events
        if len(pending) > MAX_PENDING_EVENTS:
            # Nobody reads the snapshots: keep the newest (the result keeps them all).
            self.events_dropped += len(pending) - MAX_PENDING_EVENTS
            del pending[:-MAX_PENDING_EVENTS]
        self.slack.record(time.perf_counter() - s0)

    def _send(self, i: int, t: float, fb: Any, sent: Any, hip: Any, misses: int) -> None:
        tick = self._tick
        self.seq += 1
        load = fb.bus_load_since(self._last_fb) if self._last_fb is not None else math.nan
        self._last_fb = fb
        if t - self._rate_t >= 0.5:
            self._rate = (i - self._rate_i) / (t - self._rate_t)
            self._rate_t, self._rate_i = t, i
        rate = self._rate
        reaction, res, guard = tick.reaction, tick.result, tick.loop.guard
        pending = tick.pending_events
        self._out.send(
            ControlSnapshot(
                self.seq,
                i,
                t,
                tick.state.value,
                reaction.level.name,
                reaction.source,
                reaction.reason[:160],
                tuple(fb.position_rad.tolist()),
                tuple(fb.velocity_rad_s.tolist()),
                tuple(sent.tolist()),
                tuple(hip.tolist()),
                constraint_force(tick.robot, sent),
                tick.d_now,
                tick.min_d,
                float(res.approach_mps),
                bool(res.fused_valid),
                tick.estimate_age(t),
                tuple((c, t - v) for c, v in tick.camera_last.items()),
                self.tick_us,
                self.tick_max,
                rate,
                misses,
                self.dropped,
                load,
                tuple(pending[:_MAX_EVENTS_PER_SNAPSHOT]),
                guard.state.label,
                guard.reason[:160],
                (rate * self._period) if self._simulated and rate > 0.0 else math.nan,
            )
        )
        # Oldest first; the rest go with the next snapshots.
        del pending[:_MAX_EVENTS_PER_SNAPSHOT]
        self.tick_max = 0.0

    def record_tick(self, tick_us: float) -> None:
        """The current tick's cost (µs): its maximum since the last snapshot goes in the next."""
        self.tick_us = tick_us
        if tick_us > self.tick_max:
            self.tick_max = tick_us


def _state_text(tr: Any) -> str:
    return f"{tr.to_state.value}: {tr.reason}"


def _reaction_text(r: Any) -> str:
    return f"{r.level.name} {r.source}: {r.reason}"


def _space_text(tr: Any) -> str:
    return f"{tr.state.label}: {tr.reason}" if tr.reason else tr.state.label


def _collect(
    log: tuple[Any, ...],
    last: Any,
    into: list[tuple[float, str, str]],
    kind: str,
    text: Callable[[Any], str],
) -> Any:
    """Append the entries of ``log`` after ``last`` to ``into`` as ``(t, kind, text)`` (text cut
    to 160 characters); returns the new ``last``."""
    if not log or log[-1] is last:
        return last
    for entry in _after(log, last):
        into.append((entry.t, kind, text(entry)[:160]))
    return log[-1]


def _after(log: tuple[Any, ...], last: Any) -> list[Any]:
    """The entries of a bounded log after ``last`` (by identity), oldest first."""
    out = []
    for item in reversed(log):
        if item is last:
            break
        out.append(item)
    out.reverse()
    return out


def constraint_force(robot: Any, tau: np.ndarray) -> tuple[float, float, float]:
    """Cartesian force at the HIP for the torque beyond transparency, ``J^T f = tau - h``."""
    if not np.any(tau):
        return (0.0, 0.0, 0.0)
    jac = robot.hip_jacobian()
    f, *_ = np.linalg.lstsq(jac.T, tau - robot.nonlinear_effects(), rcond=None)
    if not np.isfinite(f).all():
        return (0.0, 0.0, 0.0)
    return (float(f[0]), float(f[1]), float(f[2]))
