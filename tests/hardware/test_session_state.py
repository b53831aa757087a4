"""Session state machine and watchdogs: every transition, every watchdog, timing by ticks.

Timing is asserted from the returned reactions and the recorded logs, with timestamps stepped at
the control period (1/800 s); nothing sleeps.
"""

from __future__ import annotations

import math

import pytest
from hapticloud.core.errors import ConfigError
from hapticloud.hardware.session import (
    CONTROL_TICK_S,
    Outcome,
    ReactionLevel,
    SessionConfig,
    SessionState,
    SessionStateMachine,
    Transition,
    WatchdogConfig,
    Watchdogs,
    apply_reaction,
)
from hypothesis import given, settings
from hypothesis import strategies as st

S = SessionState
L = ReactionLevel
DT = CONTROL_TICK_S
MAX_TICKS = 4  # the bound on any reaction, 4 ticks = 5 ms


# ----- state machine -----------------------------------------------------------------------------
def _reach(state: SessionState) -> SessionStateMachine:
    m = SessionStateMachine()
    steps = {
        S.DISCONNECTED: [],
        S.CONNECTED: [m.connect],
        S.READY: [m.connect, m.drives_ready],
        S.ENABLED: [m.connect, m.drives_ready, m.enable],
        S.FAULT: [m.connect, m.drives_ready, lambda t: m.fault(t, "drive 2 overcurrent")],
        S.EMERGENCY_STOP: [m.connect, lambda t: m.emergency_stop(t, "button")],
    }[state]
    for i, step in enumerate(steps):
        assert step(0.01 * (i + 1)).ok
    assert m.state is state
    return m


def test_full_legal_path_and_log_reasons() -> None:
    m = SessionStateMachine()
    assert m.state is S.DISCONNECTED and not m.torque_allowed
    assert m.connect(1.0, "bus up").ok
    assert m.drives_ready(1.1, "drives operational").ok
    assert not m.torque_allowed
    out = m.enable(1.2, "operator enable")
    assert out.ok and out.state is S.ENABLED and m.torque_allowed
    assert m.disable(1.3, "operator disable").ok and m.state is S.READY and not m.torque_allowed
    assert m.enable(1.4).ok
    assert m.fault(1.5, "drive 1 fault 0x2310").ok and m.state is S.FAULT
    assert not m.torque_allowed and m.fault_reason == "drive 1 fault 0x2310"
    assert m.reset(1.6, cleared=True, reason="fault acknowledged").ok
    assert m.state is S.CONNECTED and m.fault_reason == ""
    assert m.disconnect(1.7, "session end").ok and m.state is S.DISCONNECTED
    assert [(tr.t, tr.from_state, tr.to_state, tr.reason) for tr in m.log] == [
        (1.0, S.DISCONNECTED, S.CONNECTED, "bus up"),
        (1.1, S.CONNECTED, S.READY, "drives operational"),
        (1.2, S.READY, S.ENABLED, "operator enable"),
        (1.3, S.ENABLED, S.READY, "operator disable"),
        (1.4, S.READY, S.ENABLED, "enable"),
        (1.5, S.ENABLED, S.FAULT, "drive 1 fault 0x2310"),
        (1.6, S.FAULT, S.CONNECTED, "fault acknowledged"),
        (1.7, S.CONNECTED, S.DISCONNECTED, "session end"),
    ]
    assert all(isinstance(tr, Transition) for tr in m.log)
    with pytest.raises(AttributeError):
        m.log[0].reason = "edited"  # type: ignore[misc]
    assert m.since == 1.7


@pytest.mark.parametrize("state", [S.DISCONNECTED, S.CONNECTED, S.FAULT, S.EMERGENCY_STOP])
def test_enable_refused_outside_ready(state: SessionState) -> None:
    m = _reach(state)
    n = len(m.log)
    out = m.enable(1.0)
    assert not out.ok and out.state is state and "enable refused" in out.reason
    assert m.state is state and not m.torque_allowed and len(m.log) == n


def test_other_illegal_transitions_refused_with_reason() -> None:
    m = SessionStateMachine()
    for event in (m.drives_ready, m.disable, m.disconnect):
        out = event(0.1)
        assert not out.ok and out.reason
    assert not m.fault(0.1, "x").ok
    assert not m.reset(0.1, cleared=True).ok
    m.connect(0.2)
    assert not m.connect(0.3).ok
    assert not m.disable(0.3).ok
    assert not m.reset(0.3, cleared=True).ok
    assert m.log[-1].to_state is S.CONNECTED and len(m.log) == 1


@pytest.mark.parametrize("state", list(SessionState))
def test_emergency_stop_from_every_state(state: SessionState) -> None:
    m = _reach(state)
    out = m.emergency_stop(2.0, "SIGINT")
    assert out.ok and m.state is S.EMERGENCY_STOP and not m.torque_allowed
    assert m.log[-1] == Transition(2.0, state, S.EMERGENCY_STOP, "SIGINT")
    assert not m.enable(2.1).ok


@pytest.mark.parametrize("state", [S.FAULT, S.EMERGENCY_STOP])
def test_reset_only_when_cleared(state: SessionState) -> None:
    m = _reach(state)
    out = m.reset(3.0, cleared=False)
    assert not out.ok and m.state is state and "not cleared" in out.reason
    assert m.reset(3.1, cleared=True).ok and m.state is S.CONNECTED
    assert not m.torque_allowed  # back to connected: drives_ready and enable again
    assert not m.enable(3.2).ok


def test_fault_refused_when_already_safe() -> None:
    m = _reach(S.EMERGENCY_STOP)
    assert not m.fault(1.0, "late fault").ok and m.state is S.EMERGENCY_STOP
    m = _reach(S.FAULT)
    assert not m.fault(1.0, "second fault").ok and m.fault_reason == "drive 2 overcurrent"


def test_log_is_bounded() -> None:
    m = SessionStateMachine(SessionConfig(log_size=16))
    m.connect(0.0)
    for i in range(50):
        m.drives_ready(i + 0.1)
        m.disconnect(i + 0.2)
        m.connect(i + 0.3)
    assert len(m.log) == 16 and m.log[-1].t == pytest.approx(49.3)


EVENTS = st.sampled_from(
    [
        "connect",
        "drives_ready",
        "enable",
        "disable",
        "fault",
        "estop",
        "reset",
        "dirty_reset",
        "disconnect",
    ]
)


def _apply(m: SessionStateMachine, name: str, t: float) -> Outcome:
    if name == "fault":
        return m.fault(t, "injected")
    if name == "estop":
        return m.emergency_stop(t, "injected")
    if name in ("reset", "dirty_reset"):
        return m.reset(t, cleared=name == "reset")
    return getattr(m, name)(t)


@settings(max_examples=300, deadline=None)
@given(st.lists(EVENTS, max_size=40))
def test_torque_only_in_enabled_whatever_the_sequence(events: list[str]) -> None:
    m = SessionStateMachine()
    enabled_by_request = False
    for i, name in enumerate(events):
        t = 0.001 * i
        before = m.state
        out = _apply(m, name, t)
        if not out.ok:
            assert m.state is before  # a refused event changes nothing
        if name == "enable" and out.ok:
            assert before is S.READY
            enabled_by_request = True
        if m.state is not S.ENABLED:
            enabled_by_request = False
        assert m.torque_allowed == (m.state is S.ENABLED)
        assert not m.torque_allowed or enabled_by_request
        if name == "estop":
            assert m.state is S.EMERGENCY_STOP
        if name == "dirty_reset":
            assert not out.ok


# ----- watchdogs ---------------------------------------------------------------------------------
CFG = WatchdogConfig(
    camera_timeout_s=0.1,
    estimate_timeout_s=0.05,
    hold_timeout_s=0.2,
    feedback_late_s=0.003,
    feedback_lost_s=0.01,
)


def _quiet(wd: Watchdogs, k: int, **over: object):
    """One tick k with everything healthy unless overridden."""
    t = k * DT
    kw: dict[str, object] = {
        "camera_last_t": {"left": t, "right": t},
        "estimate_age_s": 0.004,
        "feedback_age_s": 0.0005,
        "heartbeat_lost": False,
        "drive_fault": False,
        "bus_off": False,
    }
    kw.update(over)
    return wd.check(t, **kw)  # type: ignore[arg-type]


def _first_tick_exceeding(start_t: float, timeout: float) -> int:
    k = 0
    while not k * DT - start_t > timeout:
        k += 1
    return k


def test_quiet_means_none() -> None:
    wd = Watchdogs(CFG)
    for k in range(100):
        r = _quiet(wd, k)
        assert r.level is L.NONE and not r.torque_off
    assert wd.log == () and wd.tick == 99 and math.isinf(wd.v_limit_m_s)


def test_camera_stops_hold_surface_within_one_tick() -> None:
    wd = Watchdogs(CFG)
    stop_k = 200
    last = stop_k * DT
    fired = None
    for k in range(400):
        t = k * DT
        left = t if k <= stop_k else last
        r = _quiet(wd, k, camera_last_t={"left": left, "right": t})
        if r.level is not L.NONE and fired is None:
            fired = k
    assert fired == _first_tick_exceeding(last, CFG.camera_timeout_s)
    timeout_at = last + CFG.camera_timeout_s
    assert 0 < fired * DT - timeout_at <= DT + 1e-12
    first = wd.log[0]
    assert first.level is L.HOLD_SURFACE and first.source == "camera:left" and first.tick == fired
    assert "left" in first.reason


def test_estimate_stale_hold_surface_within_one_tick_and_v_min() -> None:
    wd = Watchdogs(CFG)
    fresh_until = 100
    for k in range(200):
        age = 0.004 if k <= fresh_until else 0.004 + (k - fresh_until) * DT
        r = _quiet(wd, k, estimate_age_s=age)
        if r.level is L.HOLD_SURFACE:
            break
    else:
        pytest.fail("estimate watchdog never fired")
    prev_age = 0.004 + (k - 1 - fresh_until) * DT
    assert age > CFG.estimate_timeout_s >= prev_age  # fired on the first tick past the timeout
    assert r.source == "estimate" and r.tick == k
    assert wd.v_limit_m_s == CFG.hold_v_min_m_s
    # sticky while stale, clears when the estimate is fresh again
    assert _quiet(wd, k + 1, estimate_age_s=age + DT).level is L.HOLD_SURFACE
    assert _quiet(wd, k + 2, estimate_age_s=0.004).level is L.NONE
    assert [x.level for x in wd.log] == [L.HOLD_SURFACE, L.NONE]


def test_hold_escalates_to_damping_after_hold_time() -> None:
    wd = Watchdogs(CFG)
    stale_from = 10
    levels = []
    for k in range(600):
        age = 0.004 if k < stale_from else 1.0
        levels.append(_quiet(wd, k, estimate_age_s=age).level)
    hold = wd.log[0]
    damp = wd.log[1]
    assert (hold.level, hold.tick) == (L.HOLD_SURFACE, stale_from)
    assert damp.level is L.DAMPING and damp.source == "hold"
    assert damp.tick == stale_from + _first_tick_exceeding(0.0, CFG.hold_timeout_s)
    assert 0 < damp.t - (hold.t + CFG.hold_timeout_s) <= DT + 1e-12
    assert set(levels[damp.tick :]) == {L.DAMPING}  # sticky while the cause lasts
    assert wd.holding_surface and wd.v_limit_m_s == CFG.hold_v_min_m_s
    assert _quiet(wd, 600).level is L.NONE  # cause cleared: back to normal


def test_feedback_late_damping_then_lost_torque_off() -> None:
    wd = Watchdogs(CFG)
    last_fb = 50
    for k in range(120):
        age = 0.0005 if k <= last_fb else (k - last_fb) * DT
        _quiet(wd, k, feedback_age_s=age)
    late, lost = wd.log[0], wd.log[1]
    assert late.level is L.DAMPING and late.source == "feedback"
    assert late.tick == last_fb + _first_tick_exceeding(0.0, CFG.feedback_late_s)
    assert lost.level is L.TORQUE_OFF and lost.source == "feedback"
    assert lost.tick == last_fb + _first_tick_exceeding(0.0, CFG.feedback_lost_s)
    assert lost.tick - (last_fb + CFG.feedback_lost_s / DT) <= 1


@pytest.mark.parametrize(
    ("flag", "source"),
    [("heartbeat_lost", "heartbeat"), ("drive_fault", "drive_fault"), ("bus_off", "bus_off")],
)
def test_torque_off_within_four_ticks_and_latched(flag: str, source: str) -> None:
    wd = Watchdogs(CFG)
    m = _reach(S.ENABLED)
    inject = 300
    fired = None
    for k in range(inject + 20):
        t = k * DT
        r = _quiet(wd, k, **{flag: inject <= k < inject + 10})
        apply_reaction(m, r, t)
        if r.torque_off and fired is None:
            fired = k
    assert fired is not None and fired - inject <= MAX_TICKS
    assert (fired - inject) * DT <= 0.005
    off = wd.log[-1]
    assert off.level is L.TORQUE_OFF and off.source == source and off.tick == fired
    # the cause cleared 10 ticks later, but TORQUE_OFF stays until an explicit reset
    assert wd.reaction.torque_off and wd.torque_off_cleared
    assert m.state is S.FAULT and not m.torque_allowed
    assert m.log[-1].t == pytest.approx(fired * DT) and source in m.log[-1].reason
    ok, why = wd.reset((inject + 20) * DT)
    assert ok, why
    assert m.reset((inject + 20) * DT, cleared=ok).ok and m.state is S.CONNECTED
    assert _quiet(wd, inject + 21).level is L.NONE


def test_torque_off_reset_refused_while_cause_active() -> None:
    wd = Watchdogs(CFG)
    m = _reach(S.ENABLED)
    r = _quiet(wd, 0, drive_fault=True)
    apply_reaction(m, r, 0.0)
    ok, why = wd.reset(DT)
    assert not ok and "still active" in why
    assert not m.reset(DT, cleared=ok).ok and m.state is S.FAULT
    assert _quiet(wd, 1).torque_off  # latched even though the fault cleared
    ok, _ = wd.reset(2 * DT)
    assert ok and not wd.reaction.torque_off


def test_heartbeat_age_and_nan_feedback() -> None:
    wd = Watchdogs(CFG)
    assert _quiet(wd, 0, heartbeat_age_s=0.05).level is L.NONE
    r = _quiet(wd, 1, heartbeat_age_s=0.2)
    assert r.torque_off and r.source == "heartbeat"
    wd = Watchdogs(CFG)
    assert _quiet(wd, 0, feedback_age_s=math.nan).torque_off  # never received


def test_most_severe_reaction_wins_and_lists_all_active() -> None:
    wd = Watchdogs(CFG)
    r = _quiet(wd, 0, estimate_age_s=1.0, camera_last_t={"left": -1.0}, bus_off=True)
    assert r.level is L.TORQUE_OFF and r.source == "bus_off"
    assert set(r.active) == {"bus_off", "camera:left", "estimate"}


@pytest.mark.parametrize(
    "kwargs",
    [
        {"camera_timeout_s": -0.1},
        {"estimate_timeout_s": 0.0},
        {"heartbeat_timeout_s": math.nan},
        {"feedback_late_s": 0.02, "feedback_lost_s": 0.01},
    ],
)
def test_watchdog_config_validated(kwargs: dict[str, float]) -> None:
    with pytest.raises(ConfigError):
        WatchdogConfig(**kwargs)


@settings(max_examples=100, deadline=None)
@given(
    inject=st.integers(0, 200),
    flag=st.sampled_from(["heartbeat_lost", "drive_fault", "bus_off"]),
    jitter=st.floats(0.0, 0.4),
)
def test_torque_off_bound_holds_for_any_injection_tick(
    inject: int, flag: str, jitter: float
) -> None:
    wd = Watchdogs(CFG)
    for k in range(inject + MAX_TICKS + 1):
        t = (k + jitter) * DT
        r = wd.check(
            t,
            {"left": t},
            0.004,
            0.0005,
            heartbeat_lost=flag == "heartbeat_lost" and k >= inject,
            drive_fault=flag == "drive_fault" and k >= inject,
            bus_off=flag == "bus_off" and k >= inject,
        )
        if k < inject:
            assert not r.torque_off
    assert r.torque_off and r.tick - inject <= MAX_TICKS
