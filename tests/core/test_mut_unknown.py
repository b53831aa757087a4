"""The surface guard pinned down where mutation testing found it loose (docs/testing.md): the first
stop and its log entry, the speed last seen fresh (kept, and forgotten after a free proof), the
negative age, the exact boundaries of the free proof, the hold's acceleration, the held surface's
body region and float type, the reasons and times of every transition, ``configure`` and
``unknown_for_s``."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hapticloud.core.haptics import SurfacePoint
from hapticloud.core.haptics.unknown import (
    SpaceState,
    SpaceTransition,
    SurfaceGuard,
    UnknownSpaceConfig,
    free_proof_holds,
    hold_acceleration,
)

K, H, S = SpaceState.KNOWN, SpaceState.HOLDING, SpaceState.STOPPED
Q = np.zeros(6)
UP = np.array([0.0, 0.0, 1.0])
CFG = UnknownSpaceConfig(fresh_s=0.125, stop_after_s=0.5, growth_m_s=0.25, speed_factor=1.0)


def _surface(z: float = 0.0, vz: float = 0.0, region: str = "face") -> SurfacePoint:
    return SurfacePoint(np.array([0.0, 0.0, z]), UP, np.array([0.0, 0.0, vz]), region)


def test_a_new_guard_is_stopped_and_logs_its_first_stop() -> None:
    guard = SurfaceGuard(CFG)
    assert guard.state is S and guard.reason == "no surface known yet"
    assert guard.transitions == () and math.isinf(guard.unknown_for_s(0.0))
    q = [0, 1, 2, 3, 4, 5]  # integers: held as floats
    d = guard.step(2.0, None, q)
    assert d.state is S and d.surface is None and d.approach_limit_mps == 0.0
    assert d.hold_q is not None and d.hold_q.dtype == np.float64
    np.testing.assert_array_equal(d.hold_q, q)
    why = "no valid surface estimate; no surface known yet"
    assert guard.transitions == (SpaceTransition(2.0, S, why),) and guard.reason == why
    guard.step(2.1, None, q, "camera stopped")
    assert len(guard.transitions) == 1  # still stopped: nothing new logged


def test_every_transition_has_its_time_and_reason_and_known_has_none() -> None:
    guard = SurfaceGuard(CFG)
    guard.step(0.0, None, Q, "no valid estimate yet")
    guard.step(0.25, _surface(), Q)
    assert guard.state is K and guard.reason == ""
    guard.step(0.5, None, Q, "")
    assert guard.state is H and guard.reason == "no valid surface estimate"
    guard.step(0.75, None, Q, "stale")
    guard.step(1.0, None, Q, "workspace seen empty", free=True)
    assert guard.state is K and guard.reason == ""
    assert guard.transitions == (
        SpaceTransition(0.0, S, "no valid estimate yet; no surface known yet"),
        SpaceTransition(0.25, K, ""),
        SpaceTransition(0.5, H, "no valid surface estimate"),
        SpaceTransition(0.75, S, "stale; newest estimate 0.500 s old"),
        SpaceTransition(1.0, K, ""),
    )


def test_the_log_keeps_the_newest_log_size_transitions() -> None:
    guard = SurfaceGuard(UnknownSpaceConfig(log_size=8))
    for k in range(20):
        guard.step(float(k), _surface() if k % 2 else None, Q, "lost")
    assert len(guard.transitions) == 8 and guard.transitions[-1].t == 19.0


def test_the_speed_last_seen_fresh_grows_a_surface_held_still_by_the_fusion() -> None:
    guard = SurfaceGuard(CFG)
    assert guard.step(0.0, _surface(0.0, 0.5), Q).state is K
    # The fusion now holds the surface still (velocity 0) and its estimate is old.
    d = guard.step(0.01, _surface(0.0, 0.0), Q, age_s=0.25)
    assert d.state is H and d.surface is not None
    # unseen 0.25 - 0.125 s, growing at 0.25 + 1.0 * 0.5 m/s (the speed seen fresh)
    assert d.surface.centroid[2] == pytest.approx(0.125 * 0.75)
    assert d.surface.velocity[2] == pytest.approx(0.75)
    assert d.surface.body_region == "face"
    assert guard.reason == "newest estimate 250 ms old"


@pytest.mark.parametrize("start", ["new", "after_free_proof"])
def test_a_surface_never_seen_fresh_grows_by_its_own_speed_only(start: str) -> None:
    guard = SurfaceGuard(CFG)
    if start == "after_free_proof":
        guard.step(0.0, _surface(0.0, 2.0), Q)  # fast, fresh
        guard.step(0.005, None, Q, free=True)  # then nothing near: that speed is forgotten
    d = guard.step(0.01, _surface(0.0, 0.0), Q, age_s=0.25)
    assert d.state is H and d.surface is not None
    assert d.surface.centroid[2] == pytest.approx(0.125 * 0.25)


def test_the_reason_of_an_old_estimate_is_in_whole_milliseconds() -> None:
    guard = SurfaceGuard(UnknownSpaceConfig(fresh_s=0.1, stop_after_s=2.0))
    guard.step(0.0, _surface(), Q, age_s=0.9)
    assert guard.state is H and guard.reason == "newest estimate 900 ms old"


def test_a_negative_age_counts_as_zero() -> None:
    guard = SurfaceGuard(CFG)
    assert guard.step(0.0, _surface(), Q, age_s=-1.0).state is K
    assert guard.unknown_for_s(0.25) == 0.25
    assert guard.step(0.49, None, Q, "lost").state is H
    assert guard.step(0.5, None, Q, "lost").state is S


def test_unknown_for_s_is_the_age_of_the_newest_estimate() -> None:
    guard = SurfaceGuard(CFG)
    guard.step(1.0, _surface(), Q, age_s=0.0625)
    assert guard.unknown_for_s(1.25) == 0.3125
    guard.step(1.5, None, Q, free=True)
    assert math.isinf(guard.unknown_for_s(1.75))  # a free proof is no surface


def test_configure_takes_effect_on_the_next_tick_and_keeps_the_state() -> None:
    guard = SurfaceGuard(CFG)
    guard.step(0.0, _surface(), Q)
    assert guard.step(0.25, None, Q, "lost").state is H
    tighter = UnknownSpaceConfig(fresh_s=0.125, stop_after_s=0.25)
    guard.configure(tighter)
    assert guard.config is tighter and guard.state is H
    assert guard.step(0.26, None, Q, "lost").state is S


def test_a_held_surface_keeps_its_body_region_and_is_float() -> None:
    guard = SurfaceGuard(CFG)
    ints = SurfacePoint(np.array([0, 0, 1]), np.array([0, 0, 1]), np.array([0, 0, 0]), "hand")
    guard.step(0.0, ints, Q)
    d = guard.step(0.25, None, Q, "lost")
    assert d.surface is not None and d.surface.body_region == "hand"
    for v in (d.surface.centroid, d.surface.normal, d.surface.velocity):
        assert v.dtype == np.float64
    np.testing.assert_array_equal(d.surface.normal, [0.0, 0.0, 1.0])
    stopped = guard.step(0.5, None, Q, "lost")
    assert stopped.surface is not None and stopped.surface.body_region == "hand"


def test_the_free_proof_boundaries() -> None:
    cfg = UnknownSpaceConfig(min_free_m=0.125)
    hip = np.array([0.5, -0.25, 1.0])
    # exactly min_free_m to spare: holds
    assert free_proof_holds(0.25, hip, hip, 0.125, cfg)
    assert not free_proof_holds(0.25, hip, hip, 0.126, cfg)
    # the HIP moved 0.0625 m from where the proof was made (away from the origin)
    moved = hip + np.array([0.0, 0.0, 0.0625])
    assert free_proof_holds(0.3125, hip, moved, 0.125, cfg)
    assert not free_proof_holds(0.3, hip, moved, 0.125, cfg)
    # no proof (0 m free) proves nothing, even with nothing to spare
    zero = UnknownSpaceConfig(min_free_m=0.0)
    assert not free_proof_holds(0.0, hip, hip, 0.0, zero)
    assert free_proof_holds(1e-9, hip, hip, 0.0, zero)


def test_hold_acceleration_about_a_non_zero_target() -> None:
    cfg = UnknownSpaceConfig(hold_kp=100.0, hold_kd=20.0)
    q = np.array([0.5, 1.0, -0.25])
    hold = np.array([0.25, 1.0, 0.0])
    qd = np.array([0.5, -2.0, 0.0])
    np.testing.assert_allclose(hold_acceleration(q, qd, hold, cfg), [-25.0 - 10.0, 40.0, 25.0])
