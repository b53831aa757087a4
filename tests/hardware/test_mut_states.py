"""The session state machine pinned down where mutation testing found it loose (docs/testing.md):
the emergency stop's stored reason, the default reasons of every event, the refusals' words, the
time of the last transition and the log's bound."""

from __future__ import annotations

import pytest
from hapticloud.hardware.session import (
    Outcome,
    SessionConfig,
    SessionState,
    SessionStateMachine,
    Transition,
)

S = SessionState


def _enabled(t: float = 0.0) -> SessionStateMachine:
    m = SessionStateMachine(t=t)
    assert m.connect(t).ok and m.drives_ready(t).ok and m.enable(t).ok
    return m


def test_the_emergency_stop_reason_is_stored_until_reset() -> None:
    m = _enabled()
    out = m.emergency_stop(1.0, "patient pressed the button")
    assert out == Outcome(True, S.EMERGENCY_STOP, "patient pressed the button")
    assert m.fault_reason == "patient pressed the button"
    # a second stop (logged too) replaces it
    m.emergency_stop(1.5, "operator Esc")
    assert m.fault_reason == "operator Esc" and len(m.log) == 5
    refused = m.reset(2.0, cleared=False)
    assert refused.reason == "reset refused in emergency_stop: cause not cleared (operator Esc)"
    assert m.fault_reason == "operator Esc"
    assert m.reset(2.1, cleared=True).ok and m.fault_reason == ""


def test_events_without_a_reason_log_their_own_name() -> None:
    m = SessionStateMachine()
    names = []
    for event, name in (
        (m.connect, "connect"),
        (m.drives_ready, "drives_ready"),
        (m.enable, "enable"),
        (m.disable, "disable"),
        (m.disconnect, "disconnect"),
    ):
        out = event(1.0)
        assert out.ok and out.reason == name
        names.append(name)
    assert [tr.reason for tr in m.log] == names
    m.connect(2.0)
    assert m.fault(2.1, "").reason == "fault" and m.fault_reason == ""
    assert m.reset(2.2, cleared=True).reason == "reset"
    assert m.emergency_stop(2.3, "").reason == "emergency stop"
    assert m.log[-1] == Transition(2.3, S.CONNECTED, S.EMERGENCY_STOP, "emergency stop")


def test_refusals_name_the_event_the_state_and_why() -> None:
    m = SessionStateMachine()
    assert m.enable(0.0) == Outcome(
        False, S.DISCONNECTED, "enable refused in disconnected: only allowed from ready"
    )
    assert m.drives_ready(0.0).reason == (
        "drives_ready refused in disconnected: only allowed from connected"
    )
    assert m.disable(0.0).reason == "disable refused in disconnected: only allowed from enabled"
    assert m.connect(0.0).ok
    assert m.connect(0.1).reason == "connect refused in connected: only allowed from disconnected"
    assert m.reset(0.1, cleared=True).reason == (
        "reset refused in connected: only allowed from fault or emergency_stop"
    )
    m.disconnect(0.2)
    assert m.disconnect(0.3).reason == "disconnect refused in disconnected: not connected"
    assert m.fault(0.3, "overcurrent").reason == (
        "fault refused in disconnected: already safe (overcurrent)"
    )


def test_fault_is_accepted_from_every_connected_state_and_refused_when_safe() -> None:
    for steps in (1, 2, 3):
        m = SessionStateMachine()
        before = [m.connect, m.drives_ready, m.enable][:steps]
        for event in before:
            event(0.0)
        state = m.state
        out = m.fault(1.0, "encoder")
        assert out == Outcome(True, S.FAULT, "encoder")
        assert m.log[-1] == Transition(1.0, state, S.FAULT, "encoder")
        assert m.fault_reason == "encoder"
        assert m.fault(1.1, "second").reason == "fault refused in fault: already safe (second)"
        assert m.fault_reason == "encoder"


def test_a_new_machine_is_disconnected_since_its_start_without_a_fault() -> None:
    m = SessionStateMachine()
    assert (m.state, m.since, m.fault_reason, m.log) == (S.DISCONNECTED, 0.0, "", ())
    assert not m.torque_allowed


def test_since_is_the_time_of_the_last_transition_only() -> None:
    m = SessionStateMachine(t=5.0)
    assert m.since == 5.0
    m.connect(6.0)
    assert m.since == 6.0
    m.enable(7.0)  # refused: no transition
    assert m.since == 6.0
    m.emergency_stop(8.0, "x")
    assert m.since == 8.0


def test_disconnect_from_every_state_but_disconnected() -> None:
    for target in (S.CONNECTED, S.READY, S.ENABLED, S.FAULT, S.EMERGENCY_STOP):
        m = _enabled()
        if target is S.CONNECTED:
            m.disable(0.1), m.disconnect(0.1), m.connect(0.1)
        elif target is S.READY:
            m.disable(0.1)
        elif target is S.FAULT:
            m.fault(0.1, "f")
        elif target is S.EMERGENCY_STOP:
            m.emergency_stop(0.1, "e")
        assert m.state is target
        out = m.disconnect(0.5, "end")
        assert out == Outcome(True, S.DISCONNECTED, "end") and not m.torque_allowed
        assert m.log[-1] == Transition(0.5, target, S.DISCONNECTED, "end")


@pytest.mark.parametrize("size", [16, 17])
def test_the_log_keeps_the_newest_log_size_transitions(size: int) -> None:
    m = SessionStateMachine(SessionConfig(log_size=size))
    for i in range(40):
        m.emergency_stop(float(i), f"stop {i}")
    assert [tr.reason for tr in m.log] == [f"stop {i}" for i in range(40 - size, 40)]
