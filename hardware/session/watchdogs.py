"""Watchdogs: staged safe reactions to stale data, late feedback and drive faults.

Called once per control tick with explicit timestamps (pure logic, no clock, no threads). Each
call is one tick; the reaction fires on the first tick at which a timeout is exceeded, so it is
never later than one tick after the timeout (the issue allows at most 4 ticks = 5 ms at 800 Hz).

Reactions, from mild to severe (:class:`ReactionLevel`):

``HOLD_SURFACE``
    a camera stopped or the surface estimate is stale: hold the last surface and limit the
    approach speed to ``hold_v_min_m_s``.
``DAMPING``
    the hold lasted longer than ``hold_timeout_s``, or the drive feedback is late.
``TORQUE_OFF``
    drive fault, lost heartbeat, bus-off or feedback lost. Latched: it stays until the causes
    have cleared *and* :meth:`Watchdogs.reset` is called (then the state machine's ``reset``).

``HOLD_SURFACE`` and ``DAMPING`` are sticky until their cause clears (no hysteresis beyond that).
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import ClassVar

from hapticloud.core.config import StageConfig, param
from hapticloud.core.errors import ConfigError

from .states import Outcome, SessionState, SessionStateMachine

CONTROL_TICK_S = 1.0 / 800.0
"""Period of the control loop the watchdogs are checked in."""


class ReactionLevel(enum.IntEnum):
    """The staged reactions, ordered by severity."""

    NONE = 0
    HOLD_SURFACE = 1
    DAMPING = 2
    TORQUE_OFF = 3


L = ReactionLevel


@dataclass(frozen=True, slots=True)
class Reaction:
    """The reaction in force: ``level``, the watchdog that fired (``source``) and why.

    ``tick`` / ``t`` are the tick index and time at which this level was entered; ``active`` lists
    every watchdog firing at the last check.
    """

    level: ReactionLevel
    source: str
    reason: str
    tick: int
    t: float
    active: tuple[str, ...] = ()

    @property
    def torque_off(self) -> bool:
        return self.level is L.TORQUE_OFF


@dataclass(frozen=True)
class WatchdogConfig(StageConfig):
    """Timeouts of the watchdogs (all in seconds)."""

    _path: ClassVar[str] = "watchdogs"

    camera_timeout_s: float = param(
        0.1, lo=0.001, hi=5.0, unit="s", doc="no frame from a camera for longer: hold surface"
    )
    estimate_timeout_s: float = param(
        0.1,
        lo=0.001,
        hi=5.0,
        unit="s",
        doc="surface estimate older than this: hold surface (the tick's fresh_s: two 30 Hz "
        "cameras with their latency leave up to ~50 ms between estimates)",
    )
    hold_timeout_s: float = param(
        0.25, lo=0.0, hi=10.0, unit="s", doc="holding the surface for longer: damping"
    )
    hold_v_min_m_s: float = param(
        0.01, lo=0.0, hi=0.5, unit="m/s", doc="approach speed limit while holding the surface"
    )
    feedback_late_s: float = param(
        0.003, lo=0.0005, hi=1.0, unit="s", doc="drive feedback older than this: damping"
    )
    feedback_lost_s: float = param(
        0.01, lo=0.001, hi=5.0, unit="s", doc="drive feedback older than this: torque off"
    )
    heartbeat_timeout_s: float = param(
        0.1, lo=0.001, hi=5.0, unit="s", doc="no drive heartbeat for longer: torque off"
    )
    log_size: int = param(1024, lo=16, hi=1_000_000, doc="reaction changes kept in the log")

    def check(self) -> None:
        if self.feedback_lost_s <= self.feedback_late_s:
            raise ConfigError(
                f"feedback_lost_s = {self.feedback_lost_s}: must be > feedback_late_s = "
                f"{self.feedback_late_s}"
            )


_NONE_REASON = "all watchdogs quiet"


def _exceeded(age: float, timeout: float) -> bool:
    """Age beyond the timeout; NaN (never received) counts as exceeded."""
    return not age <= timeout


class Watchdogs:
    """Evaluates every watchdog once per tick and keeps the staged, sticky reaction."""

    def __init__(self, config: WatchdogConfig | None = None) -> None:
        self._config = config or WatchdogConfig()
        self._tick = -1
        self._hold_since: float | None = None
        self._reaction = Reaction(L.NONE, "", _NONE_REASON, 0, 0.0)
        self._latched: Reaction | None = None
        self._torque_off_active = False
        self._log: deque[Reaction] = deque(maxlen=self._config.log_size)

    @property
    def config(self) -> WatchdogConfig:
        return self._config

    @property
    def reaction(self) -> Reaction:
        """The reaction returned by the last :meth:`check`."""
        return self._reaction

    @property
    def tick(self) -> int:
        """Index of the last checked tick (-1 before the first)."""
        return self._tick

    @property
    def log(self) -> tuple[Reaction, ...]:
        """Every change of reaction level, oldest first (bounded to ``log_size``)."""
        return tuple(self._log)

    @property
    def v_limit_m_s(self) -> float:
        """Approach speed limit in force: inf when quiet, v_min while holding or damping, 0 off."""
        level = self._reaction.level
        if level is L.NONE:
            return math.inf
        return 0.0 if level is L.TORQUE_OFF else self._config.hold_v_min_m_s

    @property
    def holding_surface(self) -> bool:
        """A camera or the estimate is stale at the last check: keep the last surface."""
        return self._hold_since is not None

    def check(
        self,
        t: float,
        camera_last_t: Mapping[str, float],
        estimate_age_s: float,
        feedback_age_s: float,
        heartbeat_lost: bool,
        drive_fault: bool,
        bus_off: bool,
        *,
        heartbeat_age_s: float | None = None,
    ) -> Reaction:
        """Evaluate every watchdog at time ``t`` (one control tick) and return the reaction.

        ``camera_last_t`` maps a camera name to the time of its last frame; ages are in seconds
        (NaN or inf: never received). ``heartbeat_lost`` is the link's verdict; when
        ``heartbeat_age_s`` is given it is also compared with ``heartbeat_timeout_s``.
        """
        cfg = self._config
        self._tick += 1
        firing: list[tuple[ReactionLevel, str, str]] = []

        # torque off: drive faults, heartbeat, bus, lost feedback
        if drive_fault:
            firing.append((L.TORQUE_OFF, "drive_fault", "a drive reports a fault"))
        if heartbeat_lost:
            firing.append((L.TORQUE_OFF, "heartbeat", "drive heartbeat lost"))
        elif heartbeat_age_s is not None and _exceeded(heartbeat_age_s, cfg.heartbeat_timeout_s):
            firing.append(
                (L.TORQUE_OFF, "heartbeat", f"no heartbeat for {heartbeat_age_s * 1e3:.2f} ms")
            )
        if bus_off:
            firing.append((L.TORQUE_OFF, "bus_off", "CAN bus off"))
        if _exceeded(feedback_age_s, cfg.feedback_lost_s):
            firing.append(
                (L.TORQUE_OFF, "feedback", f"drive feedback lost ({feedback_age_s * 1e3:.2f} ms)")
            )
        elif _exceeded(feedback_age_s, cfg.feedback_late_s):
            firing.append(
                (L.DAMPING, "feedback", f"drive feedback late ({feedback_age_s * 1e3:.2f} ms)")
            )

        # hold surface: stale cameras or estimate; damping once the hold lasts too long
        stale = False
        for name, last in camera_last_t.items():
            age = t - last
            if _exceeded(age, cfg.camera_timeout_s):
                stale = True
                firing.append(
                    (L.HOLD_SURFACE, f"camera:{name}", f"no frame from {name} for {age:.3f} s")
                )
        if _exceeded(estimate_age_s, cfg.estimate_timeout_s):
            stale = True
            firing.append(
                (L.HOLD_SURFACE, "estimate", f"surface estimate {estimate_age_s:.3f} s old")
            )
        if stale:
            if self._hold_since is None:
                self._hold_since = t
            held = t - self._hold_since
            if held > cfg.hold_timeout_s:
                firing.append((L.DAMPING, "hold", f"surface held for {held:.3f} s"))
        else:
            self._hold_since = None

        self._torque_off_active = any(level is L.TORQUE_OFF for level, _, _ in firing)
        active = tuple(source for _, source, _ in firing)

        top = max(firing, key=lambda f: f[0]) if firing else (L.NONE, "", _NONE_REASON)
        if self._latched is None and self._torque_off_active:
            self._latched = Reaction(*top, self._tick, t, active)
            return self._change(self._latched)
        if self._latched is not None:
            if active != self._latched.active:
                self._latched = replace(self._latched, active=active)
            self._reaction = self._latched
            return self._latched
        current = self._reaction
        if top[0] is current.level:
            if active != current.active:
                current = replace(current, active=active)
                self._reaction = current
            return current
        return self._change(Reaction(*top, self._tick, t, active))

    def _change(self, reaction: Reaction) -> Reaction:
        self._log.append(reaction)
        self._reaction = reaction
        return reaction

    @property
    def torque_off_cleared(self) -> bool:
        """No torque-off cause was active at the last check."""
        return not self._torque_off_active

    def reset(self, t: float) -> tuple[bool, str]:
        """Release a latched TORQUE_OFF, only if its causes cleared at the last check."""
        if self._latched is None:
            return True, "nothing latched"
        if self._torque_off_active:
            return False, f"torque-off cause still active ({self._latched.reason})"
        self._latched = None
        self._change(Reaction(L.NONE, "", "torque off reset", self._tick, t))
        return True, "reset"


def apply_reaction(machine: SessionStateMachine, reaction: Reaction, t: float) -> Outcome | None:
    """Move the session to FAULT on a TORQUE_OFF reaction (no-op if already safe)."""
    if reaction.level is L.TORQUE_OFF and machine.state in (
        SessionState.CONNECTED,
        SessionState.READY,
        SessionState.ENABLED,
    ):
        return machine.fault(t, f"watchdog {reaction.source}: {reaction.reason}")
    return None
