"""The watchdogs pinned down where mutation testing found them loose (docs/testing.md): a stopped
camera starts the hold and escalates to DAMPING, the exact tick of every timeout (``>`` not
``>=``), the configurations that are refused, the list of active watchdogs kept current, the
speed limit and the torque-off flag of each level, and the FAULT the session is moved to."""

from __future__ import annotations

import math

import pytest
from hapticloud.core.errors import ConfigError
from hapticloud.hardware.session import (
    CONTROL_TICK_S,
    Reaction,
    ReactionLevel,
    SessionState,
    SessionStateMachine,
    WatchdogConfig,
    Watchdogs,
    apply_reaction,
)

L = ReactionLevel
S = SessionState
DT = CONTROL_TICK_S
# Timeouts that are exact in binary, so that "age == timeout" is exact too.
CFG = WatchdogConfig(
    camera_timeout_s=0.125,
    estimate_timeout_s=0.0625,
    hold_timeout_s=0.25,
    hold_v_min_m_s=0.02,
    feedback_late_s=0.00390625,
    feedback_lost_s=0.015625,
    heartbeat_timeout_s=0.125,
)


def _check(wd: Watchdogs, t: float, **over: object) -> Reaction:
    """One tick at ``t`` with everything healthy unless overridden."""
    kw: dict[str, object] = {
        "camera_last_t": {"left": t, "right": t},
        "estimate_age_s": 0.0,
        "feedback_age_s": 0.0,
        "heartbeat_lost": False,
        "drive_fault": False,
        "bus_off": False,
    }
    kw.update(over)
    return wd.check(t, **kw)  # type: ignore[arg-type]


def test_a_stopped_camera_holds_the_surface_then_escalates_to_damping() -> None:
    wd = Watchdogs(CFG)
    stop = 1.0  # the left camera's last frame
    t = stop
    assert _check(wd, t).level is L.NONE
    # Exactly at the timeout the camera is not yet stale.
    t = stop + CFG.camera_timeout_s
    r = _check(wd, t, camera_last_t={"left": stop, "right": t})
    assert r.level is L.NONE and not wd.holding_surface
    t_hold = t + DT
    r = _check(wd, t_hold, camera_last_t={"left": stop, "right": t_hold})
    assert (r.level, r.source, r.t) == (L.HOLD_SURFACE, "camera:left", t_hold)
    assert r.active == ("camera:left",) and wd.holding_surface
    assert wd.v_limit_m_s == CFG.hold_v_min_m_s and not r.torque_off
    # Held for exactly hold_timeout_s: still HOLD_SURFACE; one tick more: DAMPING.
    t = t_hold + CFG.hold_timeout_s
    assert _check(wd, t, camera_last_t={"left": stop, "right": t}).level is L.HOLD_SURFACE
    t += DT
    r = _check(wd, t, camera_last_t={"left": stop, "right": t})
    assert (r.level, r.source, r.t) == (L.DAMPING, "hold", t)
    assert r.active == ("camera:left", "hold")
    assert wd.v_limit_m_s == CFG.hold_v_min_m_s and not r.torque_off
    assert [x.level for x in wd.log] == [L.HOLD_SURFACE, L.DAMPING]
    # The camera comes back: the hold ends and starts afresh on the next stop.
    t += DT
    assert _check(wd, t).level is L.NONE and not wd.holding_surface
    assert math.isinf(wd.v_limit_m_s)
    t2 = t + DT
    r = _check(wd, t2, camera_last_t={"left": t2, "right": t2 - 1.0})
    assert r.level is L.HOLD_SURFACE and r.source == "camera:right"
    r = _check(wd, t2 + 2 * DT, camera_last_t={"left": t2, "right": t2 - 1.0})
    assert r.level is L.HOLD_SURFACE  # the new hold is 2 ticks old, not counted from the first


def test_a_stale_estimate_exactly_at_its_timeout_is_not_stale() -> None:
    wd = Watchdogs(CFG)
    assert _check(wd, 0.0, estimate_age_s=CFG.estimate_timeout_s).level is L.NONE
    r = _check(wd, DT, estimate_age_s=CFG.estimate_timeout_s + 1e-9)
    assert r.level is L.HOLD_SURFACE and r.source == "estimate"
    assert "0.063 s old" in r.reason


def test_feedback_timeouts_are_exceeded_only_beyond_them() -> None:
    wd = Watchdogs(CFG)
    assert _check(wd, 0.0, feedback_age_s=CFG.feedback_late_s).level is L.NONE
    r = _check(wd, DT, feedback_age_s=CFG.feedback_late_s + 1e-9)
    assert (r.level, r.source) == (L.DAMPING, "feedback") and "late" in r.reason
    r = _check(wd, 2 * DT, feedback_age_s=CFG.feedback_lost_s)
    assert r.level is L.DAMPING  # exactly at feedback_lost_s: still only late
    r = _check(wd, 3 * DT, feedback_age_s=CFG.feedback_lost_s + 1e-9)
    assert (r.level, r.source) == (L.TORQUE_OFF, "feedback") and "lost" in r.reason
    assert r.torque_off and wd.v_limit_m_s == 0.0


def test_heartbeat_age_exactly_at_its_timeout_is_not_lost() -> None:
    wd = Watchdogs(CFG)
    assert _check(wd, 0.0, heartbeat_age_s=CFG.heartbeat_timeout_s).level is L.NONE
    r = _check(wd, DT, heartbeat_age_s=CFG.heartbeat_timeout_s + 1e-9)
    assert (r.level, r.source) == (L.TORQUE_OFF, "heartbeat")
    assert r.reason == "no heartbeat for 125.00 ms"
    # the link's verdict wins over a fresh age
    wd = Watchdogs(CFG)
    r = _check(wd, 0.0, heartbeat_lost=True, heartbeat_age_s=0.0)
    assert r.reason == "drive heartbeat lost" and r.active == ("heartbeat",)


@pytest.mark.parametrize("late", [0.004, 0.01])
def test_feedback_lost_equal_to_late_is_refused(late: float) -> None:
    # Equal timeouts would skip DAMPING (the lost check comes first).
    with pytest.raises(ConfigError, match=r"^feedback_lost_s"):
        WatchdogConfig(feedback_late_s=late, feedback_lost_s=late)
    ok = WatchdogConfig(feedback_late_s=late, feedback_lost_s=late * 1.5)
    assert ok.feedback_lost_s > ok.feedback_late_s


def test_zero_hold_timeout_damps_on_the_next_stale_tick() -> None:
    wd = Watchdogs(WatchdogConfig(hold_timeout_s=0.0))
    assert _check(wd, 0.0, estimate_age_s=1.0).level is L.HOLD_SURFACE  # held 0 s, not > 0
    assert _check(wd, DT, estimate_age_s=1.0).level is L.DAMPING


def test_the_active_list_follows_every_check_at_an_unchanged_level() -> None:
    wd = Watchdogs(CFG)
    r1 = _check(wd, 0.0, estimate_age_s=1.0)
    assert r1.level is L.HOLD_SURFACE and r1.active == ("estimate",)
    r2 = _check(wd, DT, estimate_age_s=1.0, camera_last_t={"left": -1.0, "right": DT})
    assert r2.level is L.HOLD_SURFACE and r2.active == ("camera:left", "estimate")
    assert (r2.tick, r2.t, r2.source) == (r1.tick, r1.t, r1.source)  # the level's entry
    assert wd.reaction == r2 and len(wd.log) == 1
    r3 = _check(wd, 2 * DT, estimate_age_s=1.0)
    assert r3.active == ("estimate",) and wd.reaction.active == ("estimate",)
    # quiet: no active watchdog; the reason says so
    r4 = _check(wd, 3 * DT)
    assert (r4.level, r4.active, r4.reason, r4.source) == (L.NONE, (), "all watchdogs quiet", "")


def test_a_latched_torque_off_keeps_its_cause_and_lists_what_is_active_now() -> None:
    wd = Watchdogs(CFG)
    assert wd.tick == -1 and wd.reaction.level is L.NONE and wd.log == ()
    off = _check(wd, 0.5, drive_fault=True, estimate_age_s=1.0)
    assert (off.level, off.source, off.tick, off.t) == (L.TORQUE_OFF, "drive_fault", 0, 0.5)
    assert off.reason == "a drive reports a fault" and off.active == ("drive_fault", "estimate")
    r = _check(wd, 0.5 + DT, estimate_age_s=1.0)
    assert r.level is L.TORQUE_OFF and r.source == "drive_fault" and r.tick == 0
    assert r.active == ("estimate",) and wd.reaction.active == ("estimate",)
    assert wd.torque_off_cleared and wd.tick == 1
    r = _check(wd, 0.5 + 2 * DT)
    assert r.level is L.TORQUE_OFF and r.active == ()
    assert len(wd.log) == 1
    ok, why = wd.reset(0.6)
    assert (ok, why) == (True, "reset")
    back = wd.reaction
    assert (back.level, back.reason, back.tick, back.t) == (L.NONE, "torque off reset", 2, 0.6)
    assert wd.log[-1] == back
    assert wd.reset(0.7) == (True, "nothing latched")


def test_reset_is_refused_while_a_cause_is_active_and_names_it() -> None:
    wd = Watchdogs(CFG)
    _check(wd, 0.0, bus_off=True)
    assert not wd.torque_off_cleared
    ok, why = wd.reset(0.1)
    assert not ok and why == "torque-off cause still active (CAN bus off)"
    assert wd.reaction.torque_off


def test_torque_off_flag_and_speed_limit_per_level() -> None:
    for level in ReactionLevel:
        r = Reaction(level, "x", "y", 0, 0.0)
        assert r.torque_off == (level is L.TORQUE_OFF)
    wd = Watchdogs(CFG)
    assert math.isinf(wd.v_limit_m_s)
    _check(wd, 0.0, feedback_age_s=0.01)
    assert wd.reaction.level is L.DAMPING and wd.v_limit_m_s == CFG.hold_v_min_m_s


def test_the_log_is_bounded_to_log_size() -> None:
    wd = Watchdogs(WatchdogConfig(log_size=16))
    for k in range(40):
        _check(wd, k * DT, estimate_age_s=1.0 if k % 2 else 0.0)
    assert len(wd.log) == 16 and wd.log[-1].tick == 39
    assert wd.config.log_size == 16


@pytest.mark.parametrize("state", [S.CONNECTED, S.READY, S.ENABLED])
def test_torque_off_faults_every_connected_state(state: SessionState) -> None:
    m = SessionStateMachine()
    steps = {S.CONNECTED: 1, S.READY: 2, S.ENABLED: 3}[state]
    for event in (m.connect, m.drives_ready, m.enable)[:steps]:
        assert event(0.0).ok
    off = Reaction(L.TORQUE_OFF, "bus_off", "CAN bus off", 3, 1.25)
    out = apply_reaction(m, off, 1.5)
    assert out is not None and out.ok and m.state is S.FAULT
    assert m.fault_reason == "watchdog bus_off: CAN bus off"
    assert m.log[-1].t == 1.5


def test_milder_reactions_and_safe_states_are_left_alone() -> None:
    m = SessionStateMachine()
    m.connect(0.0), m.drives_ready(0.0), m.enable(0.0)
    for level in (L.NONE, L.HOLD_SURFACE, L.DAMPING):
        assert apply_reaction(m, Reaction(level, "hold", "x", 0, 0.0), 1.0) is None
        assert m.state is S.ENABLED
    off = Reaction(L.TORQUE_OFF, "feedback", "lost", 0, 0.0)
    for reach in (lambda: None, lambda: m.emergency_stop(2.0, "button")):
        reach()
        before = m.state
        n = len(m.log)
        if before in (S.DISCONNECTED, S.EMERGENCY_STOP):
            assert apply_reaction(m, off, 2.0) is None and len(m.log) == n
    m2 = SessionStateMachine()  # DISCONNECTED
    assert apply_reaction(m2, off, 0.0) is None and m2.state is S.DISCONNECTED


def test_a_new_watchdog_is_quiet_at_tick_zero() -> None:
    wd = Watchdogs(CFG)
    assert wd.reaction == Reaction(L.NONE, "", "all watchdogs quiet", 0, 0.0)
    assert wd.torque_off_cleared and wd.reset(0.0) == (True, "nothing latched")
    assert not wd.holding_surface


def test_feedback_reasons_are_in_milliseconds() -> None:
    wd = Watchdogs(CFG)
    assert _check(wd, 0.0, feedback_age_s=0.009).reason == "drive feedback late (9.00 ms)"
    assert _check(wd, DT, feedback_age_s=0.5).reason == "drive feedback lost (500.00 ms)"


def test_the_first_of_equally_severe_watchdogs_is_the_source() -> None:
    wd = Watchdogs(CFG)
    r = _check(wd, 0.0, drive_fault=True, heartbeat_lost=True, bus_off=True)
    assert (r.source, r.reason) == ("drive_fault", "a drive reports a fault")
    assert r.active == ("drive_fault", "heartbeat", "bus_off")
    wd = Watchdogs(CFG)
    r = _check(wd, 0.0, camera_last_t={"right": -1.0, "left": 0.0}, estimate_age_s=1.0)
    assert r.source == "camera:right" and r.active == ("camera:right", "estimate")


def test_the_reset_reaction_has_no_source() -> None:
    wd = Watchdogs(CFG)
    _check(wd, 0.0, bus_off=True)
    _check(wd, DT)
    assert wd.reset(2 * DT) == (True, "reset")
    assert wd.reaction == Reaction(L.NONE, "", "torque off reset", 1, 2 * DT)
