"""Session layer: the state machine (who may command torque) and the watchdogs (staged reactions).

Pure logic driven by explicit timestamps, meant to be called by the control process every tick.
"""

from __future__ import annotations

from .states import Outcome, SessionConfig, SessionState, SessionStateMachine, Transition
from .watchdogs import (
    CONTROL_TICK_S,
    Reaction,
    ReactionLevel,
    WatchdogConfig,
    Watchdogs,
    apply_reaction,
)

__all__ = [
    "CONTROL_TICK_S",
    "Outcome",
    "Reaction",
    "ReactionLevel",
    "SessionConfig",
    "SessionState",
    "SessionStateMachine",
    "Transition",
    "WatchdogConfig",
    "Watchdogs",
    "apply_reaction",
]
