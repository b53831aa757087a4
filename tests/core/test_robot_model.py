"""The robot model: URDF parsing, HIP kinematics against finite differences, dynamics, capsules."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from hapticloud.core.errors import ConfigError, InputError
from hapticloud.core.geometry import Capsule
from hapticloud.core.robot import RobotModel, default_urdf_path, parse_link_capsules

EXPECTED_JOINTS = (
    "shoulder_elevation",
    "shoulder_protraction",
    "shoulder_flexion",
    "shoulder_abduction",
    "shoulder_internal_rotation",
    "elbow_flexion",
)


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel.load()


def _random_states(model: RobotModel, count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    for _ in range(count):
        q = rng.uniform(model.q_min, model.q_max)
        qd = rng.uniform(-model.v_max, model.v_max) * 0.5
        yield q, qd


# ----- loading and limits ------------------------------------------------------------------------
def test_loads_default_asset_with_six_joints(model: RobotModel) -> None:
    assert default_urdf_path().is_file()
    assert model.n_joints == 6
    assert model.joint_names == EXPECTED_JOINTS


def test_limits_parsed_from_urdf(model: RobotModel) -> None:
    lim = model.limits
    np.testing.assert_allclose(lim.q_min, [-0.20, -0.35, -0.70, -0.40, -1.00, 0.0])
    np.testing.assert_allclose(lim.q_max, [0.35, 0.35, 2.80, 1.90, 1.50, 2.40])
    np.testing.assert_allclose(lim.v_max, [3, 3, 5, 5, 6, 6])
    np.testing.assert_allclose(lim.tau_max, [80, 80, 80, 80, 40, 30])
    assert model.q_min is lim.q_min and model.tau_max is lim.tau_max


def test_home_has_the_hand_in_front_of_the_chest(model: RobotModel) -> None:
    q = model.q_home
    assert np.all(q >= model.q_min) and np.all(q <= model.q_max)
    hip = model.hip_position_at(q)
    # GH centre at (0, 0, 1.05); the chest's front is about 0.1-0.15 m ahead of it.
    assert 0.2 < hip[0] < 0.4
    assert 0.0 < hip[1] < 0.25
    assert 0.8 < hip[2] < 1.05


def test_upper_arm_and_forearm_lengths(model: RobotModel) -> None:
    data = model.pin_model.createData()
    pin.forwardKinematics(model.pin_model, data, np.zeros(6))
    gh = data.oMi[3].translation
    elbow = data.oMi[6].translation
    handle = model.link_placements(np.zeros(6))["handle"][1]
    np.testing.assert_allclose(gh, [0.0, 0.0, 1.05], atol=1e-12)
    assert np.linalg.norm(elbow - gh) == pytest.approx(0.30)
    assert np.linalg.norm(handle - elbow) == pytest.approx(0.28)


def test_masses_are_plausible(model: RobotModel) -> None:
    masses = [inertia.mass for inertia in model.pin_model.inertias[1:]]
    assert all(0.3 <= m <= 2.6 for m in masses)


def test_missing_and_broken_files_raise_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such file"):
        RobotModel.load(tmp_path / "nope.urdf")
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link")
    with pytest.raises(ConfigError, match=r"bad\.urdf"):
        RobotModel.load(bad)


def test_missing_hip_frame_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="'tcp'"):
        RobotModel.load(default_urdf_path(), hip_frame="tcp")


# ----- per-state quantities ----------------------------------------------------------------------
def test_update_rejects_bad_input(model: RobotModel) -> None:
    with pytest.raises(InputError, match=r"^q:"):
        model.update(np.zeros(5), np.zeros(6))
    with pytest.raises(InputError, match=r"^qd:"):
        model.update(np.zeros(6), [0, 0, np.nan, 0, 0, 0])


def test_accessors_are_read_only(model: RobotModel) -> None:
    model.update(model.q_home, np.zeros(6))
    for arr in (
        model.hip_position(),
        model.hip_jacobian(),
        model.mass_matrix(),
        model.nonlinear_effects(),
        model.hip_jdot_qd(),
        model.hip_velocity(),
    ):
        with pytest.raises(ValueError):
            arr[0] = 1.0


def test_jacobian_matches_finite_differences(model: RobotModel) -> None:
    eps = 1e-6
    for q, qd in _random_states(model, 8, seed=1):
        model.update(q, qd)
        jac = model.hip_jacobian()
        fd = np.empty((3, 6))
        for i in range(6):
            dq = np.zeros(6)
            dq[i] = eps
            fd[:, i] = (model.hip_position_at(q + dq) - model.hip_position_at(q - dq)) / (2 * eps)
        np.testing.assert_allclose(jac, fd, atol=1e-8)
        np.testing.assert_allclose(model.hip_position(), model.hip_position_at(q), atol=1e-15)
        np.testing.assert_allclose(model.hip_velocity(), jac @ qd, atol=1e-15)
        np.testing.assert_allclose(model.hip_jacobian_at(q), jac, atol=1e-15)


def test_jdot_qd_matches_finite_differences(model: RobotModel) -> None:
    eps = 1e-6
    for q, qd in _random_states(model, 8, seed=2):
        model.update(q, qd)
        plus = model.hip_jacobian_at(q + eps * qd) @ qd
        minus = model.hip_jacobian_at(q - eps * qd) @ qd
        np.testing.assert_allclose(model.hip_jdot_qd(), (plus - minus) / (2 * eps), atol=1e-6)


def test_hip_acceleration_is_second_derivative_of_position(model: RobotModel) -> None:
    # Along q(t) = q + qd t + qdd t^2 / 2 the HIP's acceleration is J qdd + Jdot qd.
    rng = np.random.default_rng(3)
    q, qd = next(_random_states(model, 1, seed=3))
    qdd = rng.normal(size=6)
    model.update(q, qd)
    h = 1e-4

    def pos(t: float) -> np.ndarray:
        return model.hip_position_at(q + qd * t + 0.5 * qdd * t * t)

    fd = (pos(h) - 2 * pos(0.0) + pos(-h)) / (h * h)
    expected = model.hip_jacobian() @ qdd + model.hip_jdot_qd()
    np.testing.assert_allclose(fd, expected, atol=2e-4)


def test_mass_matrix_symmetric_positive_definite(model: RobotModel) -> None:
    for q, qd in _random_states(model, 10, seed=4):
        model.update(q, qd)
        M = model.mass_matrix()
        np.testing.assert_array_equal(M, M.T)
        assert np.linalg.eigvalsh(M).min() > 1e-4


def test_nonlinear_effects_are_rnea_with_zero_acceleration(model: RobotModel) -> None:
    for q, qd in _random_states(model, 4, seed=5):
        model.update(q, qd)
        data = model.pin_model.createData()
        rnea = pin.rnea(model.pin_model, data, q, qd, np.zeros(6))
        np.testing.assert_allclose(model.nonlinear_effects(), rnea, atol=1e-10)


def test_gravity_points_down(model: RobotModel) -> None:
    # Arm held forward horizontally: gravity pulls it down, so holding it needs positive flexion
    # torque (flexion raises the arm).
    q = np.array([0.0, 0.0, np.pi / 2, 0.0, 0.0, 0.0])
    model.update(q, np.zeros(6))
    assert model.nonlinear_effects()[2] > 5.0


def test_forward_dynamics_is_aba_and_leaves_state_alone(model: RobotModel) -> None:
    rng = np.random.default_rng(6)
    model.update(model.q_home, np.zeros(6))
    before = model.hip_position().copy()
    for q, qd in _random_states(model, 6, seed=6):
        tau = rng.uniform(-model.tau_max, model.tau_max)
        qdd = model.forward_dynamics(q, qd, tau)
        model.update(q, qd)
        expected = np.linalg.solve(model.mass_matrix(), tau - model.nonlinear_effects())
        np.testing.assert_allclose(qdd, expected, rtol=1e-9, atol=1e-9)
    model.update(model.q_home, np.zeros(6))
    model.forward_dynamics(model.q_max, model.v_max, model.tau_max)
    np.testing.assert_array_equal(model.hip_position(), before)


def test_update_and_accessors_are_cheap(model: RobotModel) -> None:
    q, qd = model.q_home, np.full(6, 0.3)
    times = []
    for _ in range(300):
        t0 = time.perf_counter()
        model.update(q, qd)
        model.hip_position(), model.hip_velocity(), model.hip_jacobian()
        model.hip_jdot_qd(), model.mass_matrix(), model.nonlinear_effects()
        times.append(time.perf_counter() - t0)
    # Measured ~16 us median; the loose bound only catches an accidental slow path.
    assert np.median(times) < 300e-6


# ----- capsules ----------------------------------------------------------------------------------
def test_capsule_specs_cover_every_moving_link(model: RobotModel) -> None:
    links = {spec.link for spec in model.capsule_specs}
    moving = {
        "girdle_elevation_link",
        "girdle_protraction_link",
        "shoulder_flexion_link",
        "shoulder_abduction_link",
        "upper_arm_link",
        "forearm_link",
        "handle",
    }
    assert moving <= links
    guided = {spec.name for spec in model.capsule_specs if spec.guided}
    assert guided == {"guided_upper_arm", "guided_forearm", "guided_hand"}
    for spec in model.capsule_specs:
        assert spec.radius_m > 0 and spec.a.shape == (3,) and spec.b.shape == (3,)


def test_link_capsules_are_the_specs_moved_to_the_world(model: RobotModel) -> None:
    q = model.q_home
    caps = model.link_capsules(q)
    assert len(caps) == len(model.capsule_specs)
    assert all(isinstance(c, Capsule) for c in caps)
    poses = model.link_placements(q)
    for spec, cap in zip(model.capsule_specs, caps, strict=True):
        rot, pos = poses[spec.link]
        np.testing.assert_allclose(cap.a, rot @ spec.a + pos, atol=1e-12)
        np.testing.assert_allclose(cap.b, rot @ spec.b + pos, atol=1e-12)
        assert cap.radius == spec.radius_m
    robot_only = model.link_capsules(q, include_guided=False)
    assert len(robot_only) == len(caps) - 3


def test_hip_sits_at_the_handle(model: RobotModel) -> None:
    q = model.q_home
    names = [spec.name for spec in model.capsule_specs]
    grip = model.link_capsules(q)[names.index("handle_grip")]
    hip = model.hip_position_at(q)
    dist = grip.signed_distance(hip[None, :])[0]
    assert 0.0 < dist < 0.04


def test_parse_cylinder_and_sphere_as_capsules() -> None:
    urdf = """<robot name="t"><link name="l">
      <collision name="c"><origin xyz="0 0 0.5" rpy="0 1.5707963267948966 0"/>
        <geometry><cylinder radius="0.1" length="0.4"/></geometry></collision>
      <collision name="guided_s"><origin xyz="1 2 3"/><geometry><sphere radius="0.2"/></geometry>
      </collision></link></robot>"""
    cyl, sph = parse_link_capsules(urdf)
    np.testing.assert_allclose(cyl.a, [-0.2, 0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(cyl.b, [0.2, 0.0, 0.5], atol=1e-12)
    assert cyl.radius_m == 0.1 and not cyl.guided and cyl.link == "l"
    np.testing.assert_array_equal(sph.a, [1, 2, 3])
    np.testing.assert_array_equal(sph.b, [1, 2, 3])
    assert sph.guided


def test_parse_rejects_unsupported_geometry() -> None:
    urdf = """<robot name="t"><link name="l"><collision name="b">
      <geometry><box size="1 1 1"/></geometry></collision></link></robot>"""
    with pytest.raises(ConfigError, match="'box'"):
        parse_link_capsules(urdf)


def _joint_origin(model: RobotModel, q: np.ndarray, joint: str) -> np.ndarray:
    data = model.pin_model.createData()
    pin.forwardKinematics(model.pin_model, data, q)
    return data.oMi[model.pin_model.getJointId(joint)].translation.copy()


def test_positive_angles_mean_what_the_joint_names_say(model: RobotModel) -> None:
    def moved(joint: str, base: np.ndarray, point: str) -> np.ndarray:
        q = base.copy()
        q[model.joint_names.index(joint)] += 0.2
        return _joint_origin(model, q, point) - _joint_origin(model, base, point)

    zero = np.zeros(6)
    assert moved("shoulder_elevation", zero, "shoulder_flexion")[2] > 0  # shoulder up
    assert moved("shoulder_protraction", zero, "shoulder_flexion")[0] > 0  # shoulder forward
    assert moved("shoulder_flexion", zero, "elbow_flexion")[0] > 0  # elbow forward
    assert moved("shoulder_abduction", zero, "elbow_flexion")[1] < 0  # elbow out to the right
    bent = np.array([0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2])
    hand = model.hip_position_at
    q_in = bent.copy()
    q_in[4] += 0.2
    assert hand(q_in)[1] > hand(bent)[1]  # internal rotation: hand towards the belly (+y)
    q_bend = bent.copy()
    q_bend[5] += 0.2
    assert hand(q_bend)[2] > hand(bent)[2]  # more elbow flexion lifts the hand
