"""Unknown is not free: the surface guard (unit and property tests) and the closed loop under
dropouts, delays and decimations, judged against the simulator's truth."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from hapticloud.core.haptics import SurfacePoint
from hapticloud.core.haptics.unknown import (
    SpaceState,
    SurfaceGuard,
    UnknownSpaceConfig,
    free_proof_holds,
    hold_acceleration,
)
from hapticloud.core.scene import load_scene
from hapticloud.core.studies.verdict import UNSAFE_EXIT_CODE, judge
from hypothesis import given, settings
from hypothesis import strategies as st

Q = np.zeros(6)
UP = np.array([0.0, 0.0, 1.0])


def _surface(z: float = 0.0, vz: float = 0.0) -> SurfacePoint:
    return SurfacePoint(np.array([0.0, 0.0, z]), UP, np.array([0.0, 0.0, vz]), "face")


def test_nothing_known_yet_stops_at_once() -> None:
    guard = SurfaceGuard()
    d = guard.step(0.0, None, Q, "no valid estimate yet")
    assert d.state is SpaceState.STOPPED and d.surface is None and d.hold_q is not None
    assert d.approach_limit_mps == 0.0
    assert "no surface known yet" in guard.reason


def test_known_then_held_grown_then_stopped_then_known_again() -> None:
    cfg = UnknownSpaceConfig(
        fresh_s=0.05, stop_after_s=0.3, growth_m_s=0.1, speed_factor=0.5, approach_m_s=0.04
    )
    guard = SurfaceGuard(cfg)
    live = guard.step(0.0, _surface(0.0, 0.2), Q)
    assert live.state is SpaceState.KNOWN and live.approach_limit_mps is None
    held = guard.step(0.1, None, Q, "stale")
    assert held.state is SpaceState.HOLDING and held.hold_q is None
    assert held.approach_limit_mps == 0.04
    # Moved on with its last velocity (0.2 m/s) and grown by (0.1 - 0.05) * (0.1 + 0.5 * 0.2) m.
    assert held.surface is not None
    assert held.surface.centroid[2] == pytest.approx(0.1 * 0.2 + 0.05 * (0.1 + 0.5 * 0.2))
    assert held.surface.velocity[2] == pytest.approx(0.2 + 0.1 + 0.5 * 0.2)
    assert guard.step(0.29, None, Q, "stale").state is SpaceState.HOLDING
    q_stop = np.full(6, 0.3)
    stopped = guard.step(0.3, None, q_stop, "stale")
    assert stopped.state is SpaceState.STOPPED and stopped.approach_limit_mps == 0.0
    assert stopped.hold_q is not None and np.array_equal(stopped.hold_q, q_stop)
    assert stopped.surface is not None and not stopped.surface.velocity.any()  # frozen
    # The hold target does not creep with the arm.
    later = guard.step(0.5, None, Q, "stale")
    assert later.hold_q is not None and np.array_equal(later.hold_q, q_stop)
    again = guard.step(0.6, _surface(0.01), Q)
    assert again.state is SpaceState.KNOWN and again.hold_q is None
    assert [tr.state for tr in guard.transitions] == [
        SpaceState.KNOWN,
        SpaceState.HOLDING,
        SpaceState.STOPPED,
        SpaceState.KNOWN,
    ]
    assert guard.transitions[2].reason.startswith("stale; newest estimate 0.300 s old")


def test_an_old_surface_is_held_grown_by_its_age_and_stops_by_its_age() -> None:
    cfg = UnknownSpaceConfig(fresh_s=0.1, stop_after_s=0.3, growth_m_s=0.2, speed_factor=0.0)
    guard = SurfaceGuard(cfg)
    assert guard.step(0.0, _surface(), Q, age_s=0.1).state is SpaceState.KNOWN
    old = guard.step(0.01, _surface(), Q, age_s=0.16)
    assert old.state is SpaceState.HOLDING and old.approach_limit_mps == cfg.approach_m_s
    assert old.surface is not None and old.surface.centroid[2] == pytest.approx(0.06 * 0.2)
    assert guard.reason == "newest estimate 160 ms old"
    # The estimate's age, not the time since the last tick with a surface, decides the stop.
    assert guard.step(0.12, None, Q, "stale").state is SpaceState.HOLDING  # 0.27 s
    assert guard.step(0.15, None, Q, "stale").state is SpaceState.STOPPED  # 0.30 s


def test_free_proof_counts_only_while_the_hip_stays_inside_it() -> None:
    cfg = UnknownSpaceConfig(min_free_m=0.03)
    hip0 = np.zeros(3)
    assert free_proof_holds(0.15, hip0, hip0, 0.04, cfg)
    assert free_proof_holds(0.15, hip0, np.array([0.079, 0.0, 0.0]), 0.04, cfg)
    assert not free_proof_holds(0.15, hip0, np.array([0.081, 0.0, 0.0]), 0.04, cfg)
    assert not free_proof_holds(0.0, hip0, hip0, 0.04, cfg)
    assert not free_proof_holds(0.15, None, hip0, 0.04, cfg)
    guard = SurfaceGuard(cfg)
    d = guard.step(0.0, None, Q, "workspace seen empty", free=True)
    assert d.state is SpaceState.KNOWN and d.surface is None
    # A lapsed proof leaves nothing to hold: stop at once.
    assert guard.step(0.01, None, Q, "stale").state is SpaceState.STOPPED


@pytest.mark.parametrize("age", [math.nan, math.inf])
def test_a_surface_of_unknown_age_is_not_knowledge(age: float) -> None:
    guard = SurfaceGuard()
    d = guard.step(0.0, _surface(), Q, age_s=age)
    assert d.state is SpaceState.STOPPED and "unknown age" in guard.reason


def test_hold_acceleration_pulls_back_and_damps() -> None:
    cfg = UnknownSpaceConfig(hold_kp=100.0, hold_kd=20.0)
    qdd = hold_acceleration(np.full(6, 0.1), np.full(6, -1.0), np.zeros(6), cfg)
    np.testing.assert_allclose(qdd, -100.0 * 0.1 + 20.0)


@settings(max_examples=200, deadline=None)
@given(
    steps=st.lists(
        st.tuples(
            st.floats(1e-4, 0.2),  # time step
            st.booleans(),  # a valid surface this tick
            st.floats(-0.5, 0.5),  # its height
            st.floats(-2.0, 2.0),  # its vertical speed
        ),
        min_size=1,
        max_size=40,
    ),
    stop_after=st.floats(0.0, 1.0),
    fresh=st.floats(0.0, 0.5),
    age=st.floats(0.0, 0.5),
)
def test_guard_properties(
    steps: list[tuple[float, bool, float, float]], stop_after: float, fresh: float, age: float
) -> None:
    """KNOWN only with a fresh surface; the held surface is never farther from the HIP than the
    last one moved on; STOPPED exactly once the newest estimate is ``stop_after_s`` old; no
    NaN."""
    guard = SurfaceGuard(UnknownSpaceConfig(stop_after_s=stop_after, fresh_s=fresh))
    t, last, last_t, held_q = 0.0, None, None, None
    for k, (dt, valid, z, vz) in enumerate(steps):
        t += dt
        q = np.full(6, float(k))  # the arm drifts: the hold must keep where it stopped
        d = guard.step(t, _surface(z, vz) if valid else None, q, "lost", age_s=age)
        if d.state is SpaceState.STOPPED:
            assert d.hold_q is not None
            if held_q is not None:
                assert np.array_equal(d.hold_q, held_q)
            held_q = d.hold_q
        else:
            held_q = None
        if valid:
            last, last_t = _surface(z, vz), t
            if age <= fresh:
                assert d.state is SpaceState.KNOWN and d.surface is not None
                continue
        assert d.state is not SpaceState.KNOWN
        if last is None or (t - last_t) + age >= stop_after:
            assert d.state is SpaceState.STOPPED and d.hold_q is not None
        else:
            assert d.state is SpaceState.HOLDING and d.surface is not None
            moved = last.centroid[2] + (t - last_t) * last.velocity[2]
            assert d.surface.centroid[2] >= moved - 1e-12  # grown toward the HIP (above)
        if d.surface is not None:
            assert np.all(np.isfinite(d.surface.centroid))


def test_judge_names_the_worst_moment_and_why() -> None:
    t = np.arange(5) * 0.1
    margin = np.array([0.01, 0.0, -0.003, -0.001, 0.002])
    space = np.array([0, 1, 1, 0, 0], dtype=float)
    v = judge(t, margin, space=space)
    assert v.safe is False and v.exit_code == UNSAFE_EXIT_CODE
    assert v.line() == (
        "UNSAFE: min margin -3.0 mm at t=0.20 s (allowed -2.0 mm; reason: space holding for 100 ms)"
    )
    ok = judge(t, np.maximum(margin, -0.0019))
    assert ok.safe and ok.exit_code == 0 and ok.line().startswith("SAFE: min margin -1.9 mm")
    none = judge(t, np.full(5, math.inf))
    assert none.safe is None and none.line().startswith("NO TRUTH")


# ----- the closed loop -------------------------------------------------------------------------


def _margin(overrides: dict[str, object], duration: float) -> tuple[float, str]:
    from hapticloud.core.studies.run import report, run_scene

    rep = report(run_scene("demo", overrides, duration))
    return rep["min_margin_m"], rep["truth"]["line"]


def _every_camera(**values: object) -> dict[str, object]:
    """``values`` set on each of the demo's cameras, whatever their names."""
    names = [c.name for c in load_scene("demo").cameras]
    return {f"cameras.{name}.{key}": value for name in names for key, value in values.items()}


@pytest.mark.parametrize(
    "values",
    [{"decimation": 4}, {"decimation": 16}, {"stop_s": 1.0}],
    ids=["decimation-4", "decimation-16", "cameras-stop"],
)
def test_degraded_cameras_keep_the_hand_out(values: dict[str, object]) -> None:
    margin, line = _margin(_every_camera(**values), 3.0)
    assert margin >= -0.002, line


@settings(max_examples=3, deadline=None, derandomize=True)
@given(
    drop=st.sampled_from([0.0, 0.3, 0.6]),
    latency=st.sampled_from([0.015, 0.1, 0.3]),
    decimation=st.sampled_from([2, 4, 8]),
)
def test_random_dropouts_delays_and_decimations_stay_safe(
    drop: float, latency: float, decimation: int
) -> None:
    sets = _every_camera(drop_fraction=drop, latency_s=latency, decimation=decimation)
    margin, line = _margin(sets, 2.6)
    assert margin >= -0.002, line


def test_an_unsafe_run_exits_with_its_own_code() -> None:
    """The wall scene with every haptic constraint switched off goes through the wall."""
    off = [
        "--set",
        "haptics.positional_enabled=false",
        "--set",
        "haptics.velocity_enabled=false",
        "--set",
        "haptics.force_enabled=false",
    ]
    cmd = [sys.executable, "-m", "hapticloud.app.cli", "run", "wall", "--duration", "2", *off]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == UNSAFE_EXIT_CODE, done.stderr
    assert done.stdout.strip().splitlines()[-1].startswith("UNSAFE: min margin")


def test_bench_safety_prints_the_table_and_its_verdicts(tmp_path) -> None:
    out = tmp_path / "cells.json"
    cmd = [
        sys.executable,
        "-m",
        "hapticloud.app.cli",
        "bench",
        "safety",
        "--scenes",
        "demo",
        "--only",
        "decimation 16, both",
        "--duration",
        "1.5",
        "--workers",
        "1",
        "--json",
        str(out),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "| decimation 16, both cameras | " in done.stdout
    assert done.stdout.strip().splitlines()[-1] == "1 of 1 runs SAFE"
    import json

    (cell,) = json.loads(out.read_text())["cells"]
    # Nothing can be resolved at decimation 16: the robot is held still the whole run.
    assert cell["verdict"] == "SAFE" and cell["stopped_fraction"] == 1.0
