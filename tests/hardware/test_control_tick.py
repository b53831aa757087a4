"""The control tick without a process, bus or clock: commands, session, watchdogs, the held
surface and the torque by state and reaction, stepped with explicit times on the impact scene's
haptic loop and made-up drive feedback."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hapticloud.core.control import ControllerConfig
from hapticloud.core.haptics.unknown import SpaceState
from hapticloud.core.perception import SurfaceEstimate
from hapticloud.core.scene import load_scene
from hapticloud.core.scene.assembly import assemble
from hapticloud.hardware.control.messages import (
    Configure,
    Disable,
    EmergencyStop,
    Enable,
    InjectFault,
    Reset,
    estimate_to_wire,
)
from hapticloud.hardware.control.tick import FAULT_RESET_TICKS, ControlTick
from hapticloud.hardware.drives import DriveTarget
from hapticloud.hardware.session import ReactionLevel, WatchdogConfig
from hapticloud.hardware.session.states import SessionState

PERIOD = 1.0 / 800.0
WD = WatchdogConfig()


@pytest.fixture
def scene():
    loaded = load_scene("impacts")
    specs = {c.name: c for c in loaded.cameras}
    loaded = loaded.with_overrides({f"cameras.{name}.model": "oracle" for name in specs})
    return assemble(loaded), specs


def make_tick(scene, **kwargs) -> ControlTick:
    sim, specs = scene
    return ControlTick(sim.loop, 6, walls=sim.walls, camera_specs=specs, t0=0.0, **kwargs)


def feedback(scene, *, qd=None, fault=False, age_s=PERIOD, complete=True):
    """The drives' feedback as the link reports it, at the scene's start pose."""
    sim, _ = scene
    return SimpleNamespace(
        position_rad=np.array(sim.q0),
        velocity_rad_s=np.zeros(6) if qd is None else np.asarray(qd, dtype=float),
        complete=complete,
        any_stale=False,
        any_fault_bit=fault,
        oldest_age_s=age_s,
        bus_off=False,
        oldest_heartbeat_age_s=0.01,
    )


def estimate(tick: ControlTick, t: float, *, camera="front", quality=1.0, seq=1):
    """A camera's valid estimate: a plane 5 cm below the HIP, facing it (wire form)."""
    tick.robot.update(np.asarray(tick.loop.robot.q), np.zeros(6))
    hip = tick.robot.hip_position()
    est = SurfaceEstimate(
        t,
        camera,
        hip + np.array([0.0, 0.0, -0.05]),
        np.array([0.0, 0.0, 1.0]),
        True,
        method="plane",
        quality=quality,
        seq=seq,
        hip=hip,
    )
    return ("estimate", estimate_to_wire(est))


def enabled(scene, **kwargs) -> ControlTick:
    """A tick stepped to READY (complete feedback) and then ENABLED."""
    tick = make_tick(scene, **kwargs)
    tick.step(0.0, feedback(scene))
    assert tick.state is SessionState.READY
    tick.step(PERIOD, feedback(scene), [Enable("test")])
    assert tick.state is SessionState.ENABLED
    return tick


def test_no_torque_before_enable_and_the_haptic_torque_after(scene):
    tick = make_tick(scene)
    tau, target = tick.step(0.0, feedback(scene, complete=False), [Enable("too early")])
    assert tick.state is SessionState.DISCONNECTED  # enable refused: no drives yet
    assert target is DriveTarget.DISABLED and not np.any(tau)
    tau, target = tick.step(PERIOD, feedback(scene))
    assert tick.state is SessionState.READY
    assert target is DriveTarget.DISABLED and not np.any(tau)
    tau, target = tick.step(2 * PERIOD, feedback(scene), [Enable("go")])
    assert tick.state is SessionState.ENABLED and tick.level is ReactionLevel.NONE
    assert target is DriveTarget.ENABLED
    assert np.any(tau) and np.array_equal(tau, tick.result.tau)
    assert [e[2:] for e in tick.events] == [("enable", ""), ("enable", "")]
    assert tick.events[-1][:2] == (2, 2 * PERIOD)
    tau, target = tick.step(3 * PERIOD, feedback(scene), [Disable()])
    assert tick.state is SessionState.READY
    assert target is DriveTarget.DISABLED and not np.any(tau)


def test_hold_surface_makes_the_fused_surface_invalid_for_the_guard_and_caps_approach(scene):
    tick = enabled(scene)
    # Both cameras report at first; then right45 falls silent while front keeps its estimates.
    tick.take_estimates([("camera", ("right45", 0.0)), estimate(tick, 0.0)])
    tick.step(0.01, feedback(scene))
    assert tick.level is ReactionLevel.NONE
    assert tick.result.fused_valid and tick.loop.approach_limit_mps is None
    tick.take_estimates([estimate(tick, 0.19, seq=2)])
    assert tick.fusion.sample(0.2).valid  # the fusion alone still has a surface ...
    tau, target = tick.step(0.2, feedback(scene))
    assert tick.level is ReactionLevel.HOLD_SURFACE
    assert tick.reaction.source == "camera:right45"
    assert not tick.result.fused_valid  # ... which the guard does not get while holding
    assert tick.loop.approach_limit_mps == WD.hold_v_min_m_s
    assert target is DriveTarget.ENABLED and np.array_equal(tau, tick.result.tau)
    tick.take_estimates([("camera", ("right45", 0.2))])
    tick.step(0.21, feedback(scene))
    assert tick.level is ReactionLevel.NONE and tick.loop.approach_limit_mps is None


def test_damping_adds_minus_damping_times_joint_velocity(scene):
    tick = enabled(scene, damping_nms=3.0)
    qd = np.array([0.1, -0.2, 0.3, 0.05, -0.1, 0.2])
    late = (WD.feedback_late_s + WD.feedback_lost_s) / 2.0
    tau, target = tick.step(0.01, feedback(scene, qd=qd, age_s=late))
    assert tick.level is ReactionLevel.DAMPING and tick.reaction.source == "feedback"
    assert target is DriveTarget.ENABLED
    assert np.array_equal(tau, tick.result.tau - 3.0 * qd)
    # DAMPING is above HOLD_SURFACE: the held surface stays, the approach stays capped.
    assert tick.loop.approach_limit_mps == WD.hold_v_min_m_s


def test_torque_off_sends_zero_torque_and_disables_the_drives(scene):
    tick = enabled(scene)
    tau, target = tick.step(0.01, feedback(scene, fault=True))
    assert tick.level is ReactionLevel.TORQUE_OFF
    assert tick.state is SessionState.FAULT
    assert target is DriveTarget.DISABLED and not np.any(tau)
    # Latched: the fault bit gone, still no torque until a reset.
    tau, target = tick.step(0.02, feedback(scene))
    assert tick.level is ReactionLevel.TORQUE_OFF and not np.any(tau)


def test_emergency_stop_quick_stops_the_drives(scene):
    tick = enabled(scene)
    tau, target = tick.step(0.01, feedback(scene), [EmergencyStop("button")])
    assert tick.state is SessionState.EMERGENCY_STOP
    assert target is DriveTarget.QUICK_STOP and not np.any(tau)
    assert tick.machine.log[-1].reason == "button"
    tick.emergency_stop(0.02, "SIGINT")
    assert tick.events[-2][2:] == ("estop", "")
    assert tick.events[-1][2:] == ("estop", "SIGINT")


def test_reset_sends_fault_reset_ticks_then_disables(scene):
    tick = enabled(scene)
    tick.step(0.01, feedback(scene, fault=True))
    assert tick.state is SessionState.FAULT
    targets = [tick.step(0.02, feedback(scene), [Reset()])[1]]
    assert tick.state is SessionState.READY  # the cause cleared: reset at once
    for j in range(FAULT_RESET_TICKS):
        tau, target = tick.step(0.03 + j * PERIOD, feedback(scene))
        targets.append(target)
        assert not np.any(tau)
    assert (
        targets == [DriveTarget.FAULT_RESET] * (FAULT_RESET_TICKS - 1) + [DriveTarget.DISABLED] * 2
    )
    assert tick.level is ReactionLevel.NONE


def test_reset_is_refused_once_the_reset_ticks_are_spent_while_the_fault_stays(scene):
    tick = enabled(scene)
    tick.step(0.01, feedback(scene, fault=True))
    tick.step(0.02, feedback(scene, fault=True), [Reset()])
    for j in range(FAULT_RESET_TICKS + 1):
        tick.step(0.03 + j * PERIOD, feedback(scene, fault=True))
    assert tick.state is SessionState.FAULT and not tick.reset_pending
    assert tick.level is ReactionLevel.TORQUE_OFF


def test_a_controller_change_is_refused_while_enabled_and_applied_otherwise(scene):
    tick = make_tick(scene)
    tick.step(0.0, feedback(scene))
    before = tick.loop.controller
    tick.step(0.01, feedback(scene), [Configure(controller=ControllerConfig())])
    assert tick.loop.controller is not before
    assert tick.pending_events[-1] == (0.01, "config", "controller applied")
    tick.step(0.02, feedback(scene), [Enable()])
    applied = tick.loop.controller
    tick.step(0.03, feedback(scene), [Configure(controller=ControllerConfig())])
    assert tick.loop.controller is applied
    assert tick.pending_events[-1] == (
        0.03,
        "config",
        "controller change refused: disable the session first",
    )
    assert tick.events[-1][2:] == ("configure", "")


def test_stale_estimates_hold_the_surface_then_damp(scene):
    tick = enabled(scene)
    tick.take_estimates([estimate(tick, 0.0)])
    tick.step(0.05, feedback(scene))
    assert tick.level is ReactionLevel.NONE
    assert tick.estimate_age(0.05) == pytest.approx(0.05)
    # Frames still come (the camera is fine), but perception delivers no estimate.
    tick.take_estimates([("camera", ("front", 0.19))])
    tick.step(0.2, feedback(scene))
    assert tick.level is ReactionLevel.HOLD_SURFACE and tick.reaction.source == "estimate"
    t_late = 0.2 + WD.hold_timeout_s + 0.01
    tick.take_estimates([("camera", ("front", t_late))])
    tick.step(t_late, feedback(scene))
    assert tick.level is ReactionLevel.DAMPING and tick.reaction.source == "hold"


def test_a_rejected_estimate_feeds_the_watchdog_but_not_the_fusion(scene):
    tick = make_tick(scene)
    assert np.isnan(tick.estimate_age(0.0))
    assert not tick.take_estimates([estimate(tick, 0.5, quality=0.1)])  # below min_quality
    assert tick.est_time == 0.5 and tick.camera_last == {"front": 0.5}
    assert not tick.fusion.sample(0.5).valid
    assert tick.take_estimates([estimate(tick, 0.6, seq=2)])
    assert tick.fusion.sample(0.6).valid


def test_min_distance_counts_the_known_surface_not_the_held_one(scene):
    tick = make_tick(scene)
    tick.take_estimates([estimate(tick, 0.0)])
    tick.step(0.0, feedback(scene))
    tick.step(0.01, feedback(scene), [Enable()])
    assert tick.result.space is SpaceState.KNOWN and tick.min_d == tick.d_now
    known = tick.min_d
    # No estimate since: at 0.2 s the guard holds the surface, grown toward the HIP by its age.
    tick.step(0.2, feedback(scene))
    assert tick.result.space is SpaceState.HOLDING
    assert tick.d_now < known - 5e-3  # the precaution ...
    assert tick.min_d == known  # ... is not a margin the panel reports


def test_min_distance_counts_only_while_enabled_and_faults_go_to_the_emulator(scene):
    injected = []
    tick = make_tick(scene, inject=injected.append)
    tick.take_estimates([estimate(tick, 0.0)])
    tick.step(0.0, feedback(scene))
    assert tick.min_d == np.inf and np.isfinite(tick.d_now)
    tick.step(0.01, feedback(scene), [Enable(), InjectFault("inject_drive_fault", (2,))])
    assert tick.min_d == tick.d_now
    assert injected == [InjectFault("inject_drive_fault", (2,))]
    assert tick.events[-1][2:] == ("inject", "inject_drive_fault")
    with pytest.raises(TypeError):
        tick.command(("enable",), 0.02, feedback(scene))


def test_estimates_stamped_at_capture_tens_of_ms_old_leave_the_loop_enabled_and_bounded(scene):
    """Estimates as a camera stamps them, with the time the robot was at the captured pose (the
    bench, ``run --hardware``): two 30 Hz cameras each delivered 15-45 ms after capture, so that
    they arrive out of order, and one frame delivered 0.5 s late. The session stays ENABLED with
    no reaction and a valid surface, each intake refits once and the window stays the window."""
    tick = enabled(scene)
    fusion = tick.fusion
    fits = []  # what each intake's refit returned
    prepare = fusion.prepare
    fusion.prepare = lambda: fits.append(prepare()) or fits[-1]
    rng = np.random.default_rng(3)
    deliveries = []
    for i, camera in enumerate(("front", "right45")):
        for m in range(45):
            captured = 0.01 + i / 60.0 + m / 30.0
            delivered = captured + (0.5 if (i, m) == (1, 20) else rng.uniform(0.015, 0.045))
            deliveries.append((delivered, captured, camera, m))
    deliveries.sort()
    arrived = [d[1] for d in deliveries]
    assert arrived != sorted(arrived)  # capture times out of order at the loop
    window_cap = int(fusion.config.window_s * 60.0) + 2
    added_intakes = 0
    k = 2
    while deliveries:
        t = k * PERIOD
        tick.step(t, feedback(scene))
        assert tick.state is SessionState.ENABLED and tick.level is ReactionLevel.NONE
        waiting = []
        while deliveries and deliveries[0][0] <= t:
            _, captured, camera, m = deliveries.pop(0)
            waiting.append(estimate(tick, captured, camera=camera, seq=m))
        if waiting:
            refits = len(fits)
            added = tick.take_estimates(waiting)
            assert len(fits) == refits + added  # one refit per intake that added
            added_intakes += added
            assert fits[-1] is not None and fits[-1].n_samples <= window_cap
        if t > 0.06:
            assert tick.result.fused_valid
            assert tick.estimate_age(t) < WD.estimate_timeout_s
        k += 1
    assert len(fits) == added_intakes > 60
    assert fusion.n_late == 1  # the frame 0.5 s late: older than the window, left out
