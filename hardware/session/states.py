"""The session state machine: which state the rig is in, and whether torque may be commanded.

States::

    DISCONNECTED -> CONNECTED -> READY -> ENABLED      (torque only in ENABLED)
          any connected state -> FAULT                 (fault(reason))
                    any state -> EMERGENCY_STOP        (emergency_stop(reason))
    FAULT / EMERGENCY_STOP -> CONNECTED                (reset, only once the cause has cleared)
                    any state -> DISCONNECTED          (disconnect)

Pure logic driven by explicit timestamps: no clock, no threads, no exceptions on the hot path. An
event that is not allowed in the current state is refused and says why (:class:`Outcome`); every
accepted event is recorded as a frozen :class:`Transition` in a bounded log.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

from hapticloud.core.config import StageConfig, param


class SessionState(enum.Enum):
    """Where the session is; torque is allowed in :attr:`ENABLED` only."""

    DISCONNECTED = "disconnected"
    CONNECTED = "connected"
    READY = "ready"
    ENABLED = "enabled"
    FAULT = "fault"
    EMERGENCY_STOP = "emergency_stop"

    @property
    def code(self) -> int:
        """The state's integer in logs and recordings (stable: never renumber)."""
        return _STATE_CODE[self.value]

    @property
    def label(self) -> str:
        """How the state is shown to a person (``EMERGENCY STOP``)."""
        return state_label(self.value)

    @classmethod
    def from_code(cls, code: int) -> SessionState:
        """The state of :attr:`code` (``ValueError`` naming an unknown one)."""
        for state in cls:
            if _STATE_CODE[state.value] == code:
                return state
        raise ValueError(f"session state code {code!r}: not one of {sorted(_STATE_CODE.values())}")


def state_label(value: str) -> str:
    """The :attr:`SessionState.label` of a state's value; any other word (``starting``, ``closed``:
    the app's states around a session) shown the same way."""
    return value.replace("_", " ").upper()


_STATE_CODE = {
    "disconnected": 0,
    "connected": 1,
    "ready": 2,
    "enabled": 3,
    "fault": 4,
    "emergency_stop": 5,
}

S = SessionState


@dataclass(frozen=True, slots=True)
class Transition:
    """One accepted event: at time ``t`` (s) the session went ``from_state`` -> ``to_state``."""

    t: float
    from_state: SessionState
    to_state: SessionState
    reason: str


class Outcome(NamedTuple):
    """What an event did: ``ok`` False means refused (state unchanged), ``reason`` says why."""

    ok: bool
    state: SessionState
    reason: str


@dataclass(frozen=True)
class SessionConfig(StageConfig):
    """Parameters of the session state machine."""

    _path: ClassVar[str] = "session"

    log_size: int = param(1024, lo=16, hi=1_000_000, doc="transitions kept in the log")


class SessionStateMachine:
    """The session's states and the events that move between them.

    Every event takes the time ``t`` (s) at which it happens and returns an :class:`Outcome`.
    """

    def __init__(self, config: SessionConfig | None = None, *, t: float = 0.0) -> None:
        self._config = config or SessionConfig()
        self._state = S.DISCONNECTED
        self._since = t
        self._log: deque[Transition] = deque(maxlen=self._config.log_size)
        self._fault_reason = ""

    # ----- queries -------------------------------------------------------------------------------
    @property
    def state(self) -> SessionState:
        return self._state

    @property
    def since(self) -> float:
        """Time of the last transition (or of construction)."""
        return self._since

    @property
    def torque_allowed(self) -> bool:
        """True only in ENABLED: the one state in which a non-zero torque may be commanded."""
        return self._state is S.ENABLED

    @property
    def fault_reason(self) -> str:
        """Reason of the last fault or emergency stop (empty once reset)."""
        return self._fault_reason

    @property
    def log(self) -> tuple[Transition, ...]:
        """The recorded transitions, oldest first (bounded to ``log_size``)."""
        return tuple(self._log)

    # ----- internals -----------------------------------------------------------------------------
    def _go(self, t: float, to: SessionState, reason: str) -> Outcome:
        self._log.append(Transition(t, self._state, to, reason))
        self._state = to
        self._since = t
        return Outcome(True, to, reason)

    def _refuse(self, event: str, why: str) -> Outcome:
        return Outcome(False, self._state, f"{event} refused in {self._state.value}: {why}")

    def _expect(self, event: str, t: float, allowed: SessionState, to: SessionState, reason: str):
        if self._state is not allowed:
            return self._refuse(event, f"only allowed from {allowed.value}")
        return self._go(t, to, reason or event)

    # ----- events --------------------------------------------------------------------------------
    def connect(self, t: float, reason: str = "") -> Outcome:
        """The bus and the drives answer: DISCONNECTED -> CONNECTED."""
        return self._expect("connect", t, S.DISCONNECTED, S.CONNECTED, reason)

    def drives_ready(self, t: float, reason: str = "") -> Outcome:
        """Drives are operational, homed and without fault: CONNECTED -> READY."""
        return self._expect("drives_ready", t, S.CONNECTED, S.READY, reason)

    def enable(self, t: float, reason: str = "") -> Outcome:
        """Explicit request to apply torque: READY -> ENABLED (refused from anywhere else)."""
        return self._expect("enable", t, S.READY, S.ENABLED, reason)

    def disable(self, t: float, reason: str = "") -> Outcome:
        """Stop applying torque, stay ready: ENABLED -> READY."""
        return self._expect("disable", t, S.ENABLED, S.READY, reason)

    def fault(self, t: float, reason: str) -> Outcome:
        """A fault (watchdog, drive): CONNECTED / READY / ENABLED -> FAULT."""
        if self._state in (S.DISCONNECTED, S.FAULT, S.EMERGENCY_STOP):
            return self._refuse("fault", f"already safe ({reason})")
        self._fault_reason = reason
        return self._go(t, S.FAULT, reason or "fault")

    def emergency_stop(self, t: float, reason: str) -> Outcome:
        """Emergency stop, accepted from every state (repeated ones are logged too)."""
        self._fault_reason = reason
        return self._go(t, S.EMERGENCY_STOP, reason or "emergency stop")

    def reset(self, t: float, *, cleared: bool, reason: str = "") -> Outcome:
        """FAULT or EMERGENCY_STOP -> CONNECTED, only when the cause has ``cleared``.

        ``cleared`` is the caller's statement that the cause is gone, e.g. the result of
        :meth:`hapticloud.hardware.session.watchdogs.Watchdogs.reset` and a released e-stop.
        """
        if self._state not in (S.FAULT, S.EMERGENCY_STOP):
            return self._refuse("reset", "only allowed from fault or emergency_stop")
        if not cleared:
            return self._refuse("reset", f"cause not cleared ({self._fault_reason})")
        self._fault_reason = ""
        return self._go(t, S.CONNECTED, reason or "reset")

    def disconnect(self, t: float, reason: str = "") -> Outcome:
        """Close the session from any connected state (no torque afterwards)."""
        if self._state is S.DISCONNECTED:
            return self._refuse("disconnect", "not connected")
        return self._go(t, S.DISCONNECTED, reason or "disconnect")
