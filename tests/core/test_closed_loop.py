"""The simulator pieces (intent, patient arm, exoskeleton plant, IK, moving bodies) and short
closed-loop runs; the paper's experiments themselves are the slow studies at the end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hapticloud.core.errors import InputError
from hapticloud.core.robot import RobotModel
from hapticloud.core.scene import load_scene
from hapticloud.core.sim.closed_loop import ClosedLoopSim, Motion
from hapticloud.core.sim.exo import ExoPlant, solve_hip_ik
from hapticloud.core.sim.patient import IntentScript, PatientArm, Waypoint, segment_time
from hapticloud.core.studies.run import PAPER_OVERRIDES, report, run_scene

DT = 1.0 / 800.0


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel.load()


def test_motion_moves_at_constant_speed_then_stops() -> None:
    m = Motion(np.array([0.0, 0.0, 2.0]), start_s=0.5, duration_s=0.25)
    assert np.all(m.displacement(0.4) == 0.0)
    np.testing.assert_allclose(m.displacement(0.6), [0, 0, 0.2])
    np.testing.assert_allclose(m.displacement(5.0), [0, 0, 0.5])
    np.testing.assert_allclose(m.velocity_at(0.6), [0, 0, 2.0])
    assert not m.velocity_at(0.8).any()


def test_intent_linear_segment_has_the_asked_speed_and_min_jerk_ends_at_rest() -> None:
    a, b = np.zeros(3), np.array([0.3, 0.0, 0.4])
    t1 = segment_time(a, b, 0.5, "linear")
    assert t1 == pytest.approx(1.0)
    script = IntentScript([Waypoint(0.0, a), Waypoint(t1, b, "linear"), Waypoint(2.0, a)])
    assert np.linalg.norm(script.velocity(0.5)) == pytest.approx(0.5)
    np.testing.assert_allclose(script.position(2.5), a)
    assert np.linalg.norm(script.velocity(1.0 + 1e-9)) < 1e-6  # min-jerk starts at rest
    np.testing.assert_allclose(script.position(1.5), (a + b) / 2, atol=1e-12)
    with pytest.raises(InputError, match="must be after"):
        IntentScript([Waypoint(1.0, a), Waypoint(1.0, b)])


def test_a_repeated_intent_plays_again_every_period_and_must_return_to_its_start() -> None:
    a, b = np.zeros(3), np.array([0.1, 0.0, 0.0])
    waypoints = [Waypoint(0.5, a), Waypoint(1.5, b), Waypoint(2.5, a)]
    once = IntentScript(waypoints)
    script = IntentScript(waypoints, repeat_s=3.0)
    for t in (0.0, 0.7, 1.0, 2.2, 2.9):
        np.testing.assert_allclose(script.position(t), once.position(t))
        for k in (1, 7, 1000):  # every period, and far on (no drift of the phase)
            np.testing.assert_allclose(script.position(t + 3.0 * k), once.position(t), atol=1e-9)
            np.testing.assert_allclose(script.velocity(t + 3.0 * k), once.velocity(t), atol=1e-9)
    np.testing.assert_allclose(once.position(4.0), a)  # once: the last waypoint is held
    np.testing.assert_allclose(script.position(np.inf), a)  # no phase at infinity: held too
    assert np.linalg.norm(script.velocity(4.0)) > 0.05  # repeated: on its way again
    with pytest.raises(InputError, match=r"repeat_s = 1.5: shorter than the waypoints .*2 s"):
        IntentScript(waypoints, repeat_s=1.5)
    with pytest.raises(InputError, match=r"patient.repeat_s = 3: the last waypoint is 100.0 mm"):
        IntentScript(waypoints[:2], repeat_s=3.0, repeat_name="patient.repeat_s")
    with pytest.raises(InputError, match="repeat_s = -1"):
        IntentScript(waypoints, repeat_s=-1.0)


def test_a_repeated_scene_is_checked_where_it_loads(tmp_path) -> None:
    scene = load_scene("demo")
    assert scene.config.patient.repeat_s == 0.0  # not repeated (see the scene file)
    # It ends resting on the chest, not where it starts: a repeat is refused, naming the field.
    with pytest.raises(InputError, match=r"patient\.repeat_s = 10: the last waypoint is 77\.8 mm"):
        ClosedLoopSim(scene.with_overrides({"patient.repeat_s": 10.0}))
    # Its two reaches alone (without the rest) return to their start: they can repeat.
    text = Path(scene.path).read_text()
    rest = text.index("[[patient.waypoints]]\nposition_m = [0.123")
    after = text.find("\n[", rest + 1)  # the tables after the resting waypoint, if any
    reaches = tmp_path / "reaches.toml"
    reaches.write_text(text[:rest] + ("" if after < 0 else text[after:]))
    twice = load_scene(reaches)
    ClosedLoopSim(twice.with_overrides({"patient.repeat_s": 8.5}))
    with pytest.raises(InputError, match=r"patient\.repeat_s = 5: shorter than"):
        ClosedLoopSim(twice.with_overrides({"patient.repeat_s": 5.0}))


def test_posture_torque_does_not_accelerate_the_hip(model: RobotModel) -> None:
    q = model.q_home + 0.1
    model.update(q, np.zeros(6))
    J, M = model.hip_jacobian(), model.mass_matrix()
    arm = PatientArm(
        IntentScript([Waypoint(0.0, np.zeros(3))]),
        mass_kg=1.0,
        stiffness_n_per_m=100.0,
        damping_n_s_per_m=10.0,
        posture=model.q_home,
        posture_stiffness_nm_per_rad=10.0,
    )
    tau = arm.posture_torque(q, np.full(6, 0.3), J, M)
    assert np.linalg.norm(tau) > 0.1
    np.testing.assert_allclose(J @ np.linalg.solve(M, tau), 0.0, atol=1e-10)


def test_plant_holds_still_under_gravity_compensation_and_reports_the_hand_force(
    model: RobotModel,
) -> None:
    plant = ExoPlant(RobotModel.load(), model.q_home, dt=DT, substeps=4, hand_mass_kg=1.5)
    start = plant.state()
    for _ in range(400):
        plant.model.update(plant.q, plant.qd)
        state = plant.step(plant.model.nonlinear_effects().copy())
    assert np.linalg.norm(state.hip - start.hip) < 1e-6
    # With a push, the sensor reading makes the robot-only model exact: M qdd + h = tau + J^T F.
    push = np.array([0.0, 5.0, -10.0])
    plant.model.update(plant.q, plant.qd)
    tau = plant.model.nonlinear_effects().copy()
    q0, qd0 = plant.q.copy(), plant.qd.copy()
    one = ExoPlant(RobotModel.load(), q0, dt=DT, substeps=1, hand_mass_kg=1.5)
    s = one.step(tau, lambda t, h, v, q, qd, J, M: (push, np.zeros(6)))
    model.update(q0, qd0)
    qdd = (s.qd - qd0) / DT
    lhs = model.mass_matrix() @ qdd + model.nonlinear_effects()
    rhs = tau + model.hip_jacobian().T @ s.hand_force
    np.testing.assert_allclose(lhs, rhs, atol=1e-8)
    assert np.linalg.norm(s.hand_force - push) > 0.1  # the hand's inertia is in the reading


def test_ik_reaches_the_head_and_reports_unreachable(model: RobotModel) -> None:
    target = np.array([0.10, 0.11, 1.30])
    q, err = solve_hip_ik(model, target)
    assert err < 1e-4
    np.testing.assert_allclose(model.hip_position_at(q), target, atol=1e-4)
    assert np.all(q >= model.q_min) and np.all(q <= model.q_max)
    _, far = solve_hip_ik(model, [1.5, 0.0, 1.0])
    assert far > 0.5


def test_cameras_are_interleaved_and_feed_the_fusion() -> None:
    scene = load_scene(
        "impacts",
        {"cameras.front.model": "oracle", "cameras.right45.model": "oracle"},
    )
    rec = ClosedLoopSim(scene).run(1.2)
    front = [f.t for f in rec.frames if f.camera == "front"]
    right = [f.t for f in rec.frames if f.camera == "right45"]
    assert np.allclose(np.diff(front), 1 / 30, atol=DT)
    assert abs((right[0] - front[0]) - 1 / 60) <= DT  # camera k of 2 fires k / (30 * 2) later
    rep = report(rec)
    assert rep["built"]["merging"] is True and rep["estimates"]["fused"]["ticks"] > 100
    assert rep["estimates"]["fused"]["centroid_mm"]["median"] < 3.0
    assert rep["min_margin_m"] > 0.0


@pytest.mark.slow
@pytest.mark.parametrize("speed", [0.5, 1.0, 1.5, 2.0])
def test_moving_surface_no_penetration_with_perception_in_the_loop(speed: float) -> None:
    """The target: min margin >= 0 at each speed (rendered cameras, ~5 s each)."""
    ours = report(run_scene("moving-surface", {"surface.speed_mps": speed}))
    assert ours["min_margin_m"] >= 0.0
    paper = report(run_scene("moving-surface", {"surface.speed_mps": speed, **PAPER_OVERRIDES}))
    assert paper["min_margin_m"] < ours["min_margin_m"]


@pytest.mark.slow
def test_impacts_and_sliding_targets() -> None:
    imp = report(run_scene("impacts"))
    assert imp["max_penetration_m"] <= 0.002 and len(imp["contacts"]) == 3
    slide = report(run_scene("sliding"))
    fused = slide["estimates"]["fused"]
    assert fused["normal_jump_deg"]["max"] <= 5.0
    assert fused["centroid_mm"]["median"] <= 2.0
