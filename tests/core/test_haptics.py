"""Haptic quantities and constraints: signs, Jacobians against finite differences, row directions,
the ISO/TS 15066 table, configuration errors and never-NaN rows (property tests)."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hapticloud.core.control.rows import Inequality
from hapticloud.core.errors import ConfigError, InputError
from hapticloud.core.haptics import (
    BODY_REGIONS,
    ForceConstraint,
    ForceConstraintConfig,
    HipState,
    PositionalConstraint,
    PositionalConstraintConfig,
    SurfacePoint,
    VelocityConstraint,
    VelocityConstraintConfig,
    approach_speed_bound,
    body_region,
    constraint_jacobian,
    contact_force_n,
    d_proj,
    effective_mass_kg,
    haptic_state,
    max_transient_speed_mps,
)
from hapticloud.core.robot import RobotModel
from hypothesis import given, settings
from hypothesis import strategies as st

DT = 1.0 / 800.0
R_HIP = 0.04
N = 6


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel.load()


def _hip(model: RobotModel, q: np.ndarray, qd: np.ndarray) -> HipState:
    model.update(q, qd)
    return HipState.from_model(model, R_HIP)


def _surface_at(
    hip: HipState, normal, distance: float, velocity=(0.0, 0.0, 0.0), region: str = ""
) -> SurfacePoint:
    """A surface whose d_proj from ``hip`` is ``distance`` (normal towards the HIP)."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    centroid = hip.position - (distance + hip.radius_m) * n
    return SurfacePoint(centroid, n, np.asarray(velocity, float), region)


def _x(qdd=None, tau=None) -> np.ndarray:
    x = np.zeros(2 * N)
    if qdd is not None:
        x[:N] = qdd
    if tau is not None:
        x[N:] = tau
    return x


def _synthetic_hip(
    jacobian, *, qd=None, jdot_qd=(0.0, 0.0, 0.0), mass=None, nle=None, position=(0.0, 0.0, 0.0)
) -> HipState:
    jac = np.asarray(jacobian, float)
    n = jac.shape[1]
    return HipState(
        np.asarray(position, float),
        np.zeros(n) if qd is None else np.asarray(qd, float),
        jac,
        np.asarray(jdot_qd, float),
        np.eye(n) if mass is None else np.asarray(mass, float),
        np.zeros(n) if nle is None else np.asarray(nle, float),
        R_HIP,
    )


# ----- d_proj and J_c ----------------------------------------------------------------------------
def test_d_proj_sign_and_value() -> None:
    c, n = np.zeros(3), np.array([0.0, 0.0, 1.0])
    assert d_proj(c, n, [0.3, -0.2, 0.10], R_HIP) == pytest.approx(0.06)
    assert d_proj(c, n, [0.0, 0.0, 0.02], R_HIP) == pytest.approx(-0.02)  # penetration
    assert d_proj(c, n, [0.0, 0.0, -0.1], 0.0) == pytest.approx(-0.1)  # behind the surface
    # The normal is normalised; its length does not matter.
    assert d_proj(c, 5 * n, [0.0, 0.0, 0.10], R_HIP) == pytest.approx(0.06)


def test_d_proj_rejects_bad_arguments() -> None:
    with pytest.raises(InputError, match=r"^normal"):
        d_proj(np.zeros(3), np.zeros(3), np.ones(3), R_HIP)
    with pytest.raises(InputError, match=r"^r_hip_m"):
        d_proj(np.zeros(3), [0, 0, 1], np.ones(3), -0.01)
    with pytest.raises(InputError, match=r"^hip"):
        d_proj(np.zeros(3), [0, 0, 1], [np.nan, 0, 0], R_HIP)


def test_constraint_jacobian_matches_finite_differences(model: RobotModel) -> None:
    rng = np.random.default_rng(10)
    eps = 1e-6
    for _ in range(5):
        q = rng.uniform(model.q_min, model.q_max)
        normal = rng.normal(size=3)
        centroid = rng.normal(size=3)
        model.update(q, np.zeros(N))
        J_c = constraint_jacobian(normal, model.hip_jacobian())
        fd = np.empty(N)
        for i in range(N):
            dq = np.zeros(N)
            dq[i] = eps
            up = d_proj(centroid, normal, model.hip_position_at(q + dq), R_HIP)
            down = d_proj(centroid, normal, model.hip_position_at(q - dq), R_HIP)
            fd[i] = (up - down) / (2 * eps)
        np.testing.assert_allclose(J_c, fd, atol=1e-8)


def test_haptic_state_rates_match_finite_differences(model: RobotModel) -> None:
    # Along q(t) = q + qd t (qdd = 0): d_dot = J_c qd and d_ddot = Jdc_qd for a still surface.
    rng = np.random.default_rng(11)
    q = rng.uniform(model.q_min, model.q_max)
    qd = rng.uniform(-1.0, 1.0, N)
    hip = _hip(model, q, qd)
    surface = _surface_at(hip, rng.normal(size=3), 0.02)
    hs = haptic_state(hip, surface)
    assert hs.d_proj == pytest.approx(0.02)

    def d(t: float) -> float:
        return d_proj(surface.centroid, surface.normal, model.hip_position_at(q + qd * t), R_HIP)

    h = 1e-4
    assert hs.d_dot_robot == pytest.approx((d(h) - d(-h)) / (2 * h), abs=1e-7)
    assert hs.Jdc_qd == pytest.approx((d(h) - 2 * d(0.0) + d(-h)) / (h * h), abs=1e-3)
    assert hs.d_dot_surface == 0.0


def test_surface_velocity_sign() -> None:
    hip = _synthetic_hip(np.eye(3))
    towards = _surface_at(hip, [0, 0, 1], 0.05, velocity=[0.3, 0.0, 0.5])  # coming up at 0.5
    assert haptic_state(hip, towards).d_dot_surface == pytest.approx(-0.5)


def test_surface_without_velocity_attribute_is_still() -> None:
    hip = _synthetic_hip(np.eye(3))
    bare = SimpleNamespace(centroid=np.array([0.0, 0.0, -0.1]), normal=np.array([0.0, 0.0, 1.0]))
    hs = haptic_state(hip, bare)
    assert hs.d_dot_surface == 0.0 and hs.d_proj == pytest.approx(0.06)
    with pytest.raises(InputError, match="surface"):
        haptic_state(hip, object())


# ----- positional --------------------------------------------------------------------------------
def test_positional_inactive_far_active_near(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    con = PositionalConstraint(PositionalConstraintConfig(activation_distance_m=0.1))
    far = con.rows(hip, _surface_at(hip, [0, -1, 0.2], 0.11), DT)
    assert isinstance(far, Inequality)
    assert far.G.shape == (0, 2 * N) and far.h.shape == (0,) and far.name == con.name
    near = con.rows(hip, _surface_at(hip, [0, -1, 0.2], 0.05), DT)
    assert near.G.shape == (1, 2 * N) and near.h.shape == (1,)
    np.testing.assert_array_equal(near.G[0, N:], 0.0)  # kinematic: no torque part


def test_positional_row_is_the_paper_inequality(model: RobotModel) -> None:
    rng = np.random.default_rng(12)
    cfg = PositionalConstraintConfig(kp=20.0, surface_velocity_feedforward=False)
    con = PositionalConstraint(cfg)
    hip = _hip(model, model.q_home, rng.uniform(-0.5, 0.5, N))
    surface = _surface_at(hip, [0.2, -1, 0.3], 0.01)
    hs = haptic_state(hip, surface)
    rows = con.rows(hip, surface, DT)
    T = cfg.kp * DT
    for _ in range(50):
        qdd = rng.normal(scale=20.0, size=N)
        predicted = hs.d_proj + T * hs.d_dot_robot + T * T / 2 * (hs.J_c @ qdd + hs.Jdc_qd)
        lhs = rows.G @ _x(qdd, rng.normal(size=N)) - rows.h
        # Same inequality, scaled by T^2/2: G x - h = -predicted / (T^2/2).
        assert lhs[0] == pytest.approx(-predicted / (T * T / 2), rel=1e-9, abs=1e-9)


def test_positional_step_that_increases_penetration_violates(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    surface = _surface_at(hip, [0, 0, 1], -0.005)  # already 5 mm in
    rows = PositionalConstraint().rows(hip, surface, DT)
    J_c = haptic_state(hip, surface).J_c
    deeper = -J_c / np.linalg.norm(J_c)  # joint acceleration direction into the surface
    out = J_c / np.linalg.norm(J_c)
    assert (rows.G @ _x(0.0 * deeper) - rows.h)[0] > 0  # at rest inside: must push out
    assert (rows.G @ _x(10.0 * deeper) - rows.h)[0] > (rows.G @ _x(0.0 * deeper) - rows.h)[0]
    assert (rows.G @ _x(1e4 * out) - rows.h)[0] < 0  # pushing out hard satisfies it


def test_positional_feedforward_shifts_h(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    surface = _surface_at(hip, [0, 0, 1], 0.02, velocity=[0.0, 0.0, 0.4])  # rising at 0.4 m/s
    with_ff = PositionalConstraint(PositionalConstraintConfig(kp=10.0))
    paper = PositionalConstraint(
        PositionalConstraintConfig(kp=10.0, surface_velocity_feedforward=False)
    )
    T = 10.0 * DT
    diff = with_ff.rows(hip, surface, DT).h[0] - paper.rows(hip, surface, DT).h[0]
    assert diff == pytest.approx(2 * T * (-0.4) / (T * T))


def test_positional_stops_an_impact_like_a_damped_spring() -> None:
    # 1-D point mass (J_c = 1) hitting a wall at 0.5 m/s; the controller does the least it
    # must: qdd = max(0, lower bound of the row).
    cfg = PositionalConstraintConfig(kp=20.0, activation_distance_m=0.1)
    con = PositionalConstraint(cfg)
    d, v = 0.05, -0.5
    deepest, states = d, []
    for _ in range(2000):
        hip = _synthetic_hip([[0.0], [0.0], [1.0]], qd=[v], position=[0.0, 0.0, d + R_HIP])
        rows = con.rows(hip, SurfacePoint(np.zeros(3), np.array([0.0, 0.0, 1.0])), DT)
        acc = 0.0
        if rows.G.shape[0]:
            acc = max(0.0, rows.h[0] / rows.G[0, 0])  # G qdd <= h, G < 0: qdd >= h / G
        v += acc * DT
        d += v * DT
        deepest = min(deepest, d)
        states.append((d, v))
    assert deepest > -0.005  # at most a few mm in
    assert deepest < 0.0  # the spring does give a little
    assert states[-1][1] >= 0.0  # bounced back (the paper's small rebound)


# ----- velocity ----------------------------------------------------------------------------------
def test_velocity_bound_piecewise() -> None:
    args = {"v_min_mps": 0.1, "v_max_mps": 1.1, "d_offset_m": 0.02, "d_width_m": 0.1}
    assert approach_speed_bound(-0.5, **args) == 0.1
    assert approach_speed_bound(0.0, **args) == 0.1
    assert approach_speed_bound(0.02, **args) == 0.1
    assert approach_speed_bound(0.07, **args) == pytest.approx(0.6)
    assert approach_speed_bound(0.12, **args) == pytest.approx(1.1)
    assert approach_speed_bound(5.0, **args) == 1.1


@pytest.mark.parametrize("width", [0.0, 1e-300, 1e-12])
def test_velocity_bound_tiny_width_is_a_step(width: float) -> None:
    args = {"v_min_mps": 0.1, "v_max_mps": 1.0, "d_offset_m": 0.05, "d_width_m": width}
    assert approach_speed_bound(0.05, **args) == 0.1
    assert approach_speed_bound(0.05 + 1e-15, **args) == 1.0
    assert approach_speed_bound(0.049, **args) == 0.1
    for d in np.linspace(0.04, 0.06, 101):
        assert math.isfinite(approach_speed_bound(float(d), **args))


def test_velocity_inactive_far_active_near(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    con = VelocityConstraint()
    far = con.rows(hip, _surface_at(hip, [1, 0, 0], con.config.activation_distance_m + 0.01), DT)
    assert far.G.shape == (0, 2 * N)
    near = con.rows(hip, _surface_at(hip, [1, 0, 0], 0.05), DT)
    assert near.G.shape == (1, 2 * N)
    np.testing.assert_array_equal(near.G[0, N:], 0.0)


def test_velocity_row_bounds_the_approach_speed_one_step_ahead(model: RobotModel) -> None:
    rng = np.random.default_rng(13)
    cfg = VelocityConstraintConfig(kv=5.0)
    con = VelocityConstraint(cfg)
    hip = _hip(model, model.q_home, rng.uniform(-0.5, 0.5, N))
    surface = _surface_at(hip, [0.3, 0.4, 1.0], 0.03, velocity=[0.1, -0.2, 0.3])
    hs = haptic_state(hip, surface)
    rows = con.rows(hip, surface, DT)
    K = cfg.kv * DT
    v_c = cfg.bound(0.03)
    for _ in range(50):
        qdd = rng.normal(scale=50.0, size=N)
        d_dot_next = hs.d_dot_robot + hs.d_dot_surface + K * (hs.J_c @ qdd + hs.Jdc_qd)
        ok_row = (rows.G @ _x(qdd) - rows.h)[0] <= 0
        assert ok_row == (-d_dot_next <= v_c + 1e-12)


def test_velocity_step_towards_surface_violates(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    surface = _surface_at(hip, [0, 0, 1], 0.0)
    rows = VelocityConstraint().rows(hip, surface, DT)
    J_c = haptic_state(hip, surface).J_c
    into = -J_c / np.linalg.norm(J_c)
    assert (rows.G @ _x(0 * into) - rows.h)[0] < 0  # at rest: fine
    assert (rows.G @ _x(1e3 * into) - rows.h)[0] > 0  # accelerating in: violates


def test_velocity_feedforward_changes_h_by_surface_speed(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    surface = _surface_at(hip, [0, 0, 1], 0.05, velocity=[0.2, 0.0, 0.6])
    base = {"kv": 4.0}
    ff = VelocityConstraint(VelocityConstraintConfig(**base)).rows(hip, surface, DT)
    paper = VelocityConstraint(
        VelocityConstraintConfig(**base, surface_velocity_feedforward=False)
    ).rows(hip, surface, DT)
    np.testing.assert_array_equal(ff.G, paper.G)
    assert ff.h[0] - paper.h[0] == pytest.approx(-0.6 / (4.0 * DT))
    # A surface moving away loosens it; tangential motion changes nothing.
    away = surface._replace(velocity=np.array([0.0, 0.0, -0.6]))
    tangential = surface._replace(velocity=np.array([0.5, -0.5, 0.0]))
    con = VelocityConstraint(VelocityConstraintConfig(**base))
    assert con.rows(hip, away, DT).h[0] - paper.h[0] == pytest.approx(0.6 / (4.0 * DT))
    assert con.rows(hip, tangential, DT).h[0] == pytest.approx(paper.h[0])


# ----- configuration errors ----------------------------------------------------------------------
@pytest.mark.parametrize(
    ("cls", "field", "value"),
    [
        (PositionalConstraintConfig, "kp", 0.0),
        (PositionalConstraintConfig, "kp", float("nan")),
        (PositionalConstraintConfig, "activation_distance_m", -0.1),
        (VelocityConstraintConfig, "kv", 0.5),
        (VelocityConstraintConfig, "v_min_mps", -0.1),
        (VelocityConstraintConfig, "d_width_m", -0.01),
        (ForceConstraintConfig, "safety_factor", 0.0),
        (ForceConstraintConfig, "safety_factor", 1.5),
        (ForceConstraintConfig, "contact", "impact"),
        (ForceConstraintConfig, "default_body_region", "tail"),
    ],
)
def test_bad_parameters_raise_config_error_naming_the_field(cls, field, value) -> None:
    with pytest.raises(ConfigError, match=f"^{field}"):
        cls(**{field: value})


def test_velocity_cross_field_rules() -> None:
    with pytest.raises(ConfigError, match=r"^v_min_mps"):
        VelocityConstraintConfig(v_min_mps=1.0, v_max_mps=0.5)
    with pytest.raises(ConfigError, match=r"^activation_distance_m"):
        VelocityConstraintConfig(d_offset_m=0.1, d_width_m=0.1, activation_distance_m=0.15)


def test_configs_round_trip_through_dicts() -> None:
    for cls in (PositionalConstraintConfig, VelocityConstraintConfig, ForceConstraintConfig):
        cfg = cls()
        assert cls.from_dict(cfg.to_dict()) == cfg
        assert dataclasses.is_dataclass(cfg)


def test_natural_frequency_of_the_positional_spring() -> None:
    cfg = PositionalConstraintConfig(kp=40.0)
    assert cfg.natural_frequency_hz(DT) == pytest.approx(math.sqrt(2) / (40 * DT) / (2 * math.pi))


def test_bad_dt_is_named(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    surface = _surface_at(hip, [0, 0, 1], 0.0)
    for con in (PositionalConstraint(), VelocityConstraint(), ForceConstraint()):
        for dt in (0.0, -DT, float("nan"), 10.0):
            with pytest.raises(InputError, match=r"^dt"):
                con.rows(hip, surface, dt)


# ----- ISO/TS 15066 ------------------------------------------------------------------------------
def test_iso_table_values() -> None:
    expected_qs = {
        "skull_forehead": 130,
        "face": 65,
        "neck": 150,
        "back_shoulders": 210,
        "chest": 140,
        "abdomen": 110,
        "pelvis": 180,
        "upper_arm_elbow": 150,
        "lower_arm_wrist": 160,
        "hand_finger": 140,
        "thigh_knee": 220,
        "lower_leg": 130,
    }
    assert {k: r.quasi_static_force_n for k, r in BODY_REGIONS.items()} == expected_qs
    assert body_region("chest").transient_force_n == 280
    assert body_region("face").transient_force_n is None
    assert body_region("skull_forehead").transient_pressure_n_per_cm2 is None
    assert body_region("chest").transient_pressure_n_per_cm2 == 240


def test_iso_lookup_by_key_alias_and_spelling() -> None:
    assert body_region("head").key == "skull_forehead"
    assert body_region("Upper arm-elbow").key == "upper_arm_elbow"
    assert body_region(" Hand ").key == "hand_finger"
    with pytest.raises(ConfigError, match="'tail'"):
        body_region("tail")


def test_iso_force_limits_by_contact_and_area() -> None:
    chest = body_region("chest")
    assert chest.force_limit_n() == 140
    assert chest.force_limit_n("transient") == 280
    assert body_region("face").force_limit_n("transient") == 65  # no transient: stricter value
    assert chest.force_limit_n("quasi_static", 1e-4) == pytest.approx(120.0)  # 120 N/cm2 x 1 cm2
    assert chest.force_limit_n("quasi_static", 1e-2) == 140  # large area: the force limit rules
    with pytest.raises(ConfigError, match="contact"):
        chest.force_limit_n("impact")


def test_iso_transient_speed() -> None:
    hand = body_region("hand")
    # v = F / sqrt(mu k), mu = m_H for a rigid robot.
    rigid = max_transient_speed_mps(hand, math.inf)
    assert rigid == pytest.approx(280.0 / math.sqrt(0.6 * 75e3))
    assert max_transient_speed_mps("hand", 2.0) > rigid  # a lighter robot may go faster
    assert max_transient_speed_mps("face", 2.0) < max_transient_speed_mps("chest", 2.0)


# ----- force -------------------------------------------------------------------------------------
def test_force_inactive_far_active_at_contact(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    con = ForceConstraint(ForceConstraintConfig(activation_distance_m=0.01))
    assert con.rows(hip, _surface_at(hip, [1, 0, 0], 0.02), DT).G.shape == (0, 2 * N)
    rows = con.rows(hip, _surface_at(hip, [1, 0, 0], 0.0), DT)
    assert rows.G.shape == (1, 2 * N)
    np.testing.assert_array_equal(rows.G[0, :N], 0.0)  # acts on tau only
    assert np.any(rows.G[0, N:] != 0.0)


def test_force_row_is_the_contact_force_bound(model: RobotModel) -> None:
    rng = np.random.default_rng(14)
    cfg = ForceConstraintConfig(safety_factor=0.5)
    con = ForceConstraint(cfg)
    hip = _hip(model, model.q_home, rng.uniform(-0.3, 0.3, N))
    surface = _surface_at(hip, [0.2, 0.1, 1.0], 0.0, region="chest")
    limit = con.force_limit_n(surface)
    assert limit == pytest.approx(70.0)
    rows = con.rows(hip, surface, DT)
    for _ in range(100):
        tau = hip.nonlinear_effects + rng.normal(scale=15.0, size=N)
        lam = contact_force_n(hip, surface, tau)
        ok = (rows.G @ _x(rng.normal(size=N), tau) - rows.h)[0] <= 0
        assert ok == (lam <= limit + 1e-9)


def test_force_of_a_cartesian_push_is_recovered(model: RobotModel) -> None:
    # Holding still against gravity and pressing with f newtons along -n.
    hip = _hip(model, model.q_home, np.zeros(N))
    surface = _surface_at(hip, [0.0, 0.3, 1.0], 0.0)
    J_c = haptic_state(hip, surface).J_c
    tau = hip.nonlinear_effects - J_c * 30.0
    assert contact_force_n(hip, surface, tau) == pytest.approx(30.0)
    assert contact_force_n(hip, surface, hip.nonlinear_effects) == pytest.approx(0.0, abs=1e-9)
    assert 0.3 < effective_mass_kg(hip, surface.normal) < 50.0


def test_force_limit_follows_the_body_region(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    con = ForceConstraint(ForceConstraintConfig(safety_factor=1.0))
    face = con.rows(hip, _surface_at(hip, [0, 0, 1], 0.0, region="face"), DT)
    unknown = con.rows(hip, _surface_at(hip, [0, 0, 1], 0.0), DT)  # default region: face
    pelvis = con.rows(hip, _surface_at(hip, [0, 0, 1], 0.0, region="pelvis"), DT)
    np.testing.assert_array_equal(face.h, unknown.h)
    assert pelvis.h[0] > face.h[0]  # a larger force is allowed on the pelvis
    with pytest.raises(ConfigError, match="'tail'"):
        con.rows(hip, _surface_at(hip, [0, 0, 1], 0.0, region="tail"), DT)


def test_force_row_vanishes_smoothly_in_a_singular_direction() -> None:
    # The HIP cannot move along n = z: J_c = 0; the row must be finite, with no torque part.
    jac = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])
    hip = _synthetic_hip(jac, jdot_qd=[0.0, 0.0, 0.3], mass=np.diag([2.0, 3.0]))
    surface = SurfacePoint(np.array([0.0, 0.0, -R_HIP]), np.array([0.0, 0.0, 1.0]))
    rows = ForceConstraint().rows(hip, surface, DT)
    assert np.all(np.isfinite(rows.G)) and np.all(np.isfinite(rows.h))
    np.testing.assert_array_equal(rows.G, 0.0)
    assert rows.h[0] == pytest.approx(0.3)
    assert math.isinf(effective_mass_kg(hip, surface.normal))
    assert math.isfinite(contact_force_n(hip, surface, np.ones(2)))


def test_force_rejects_a_mass_matrix_that_is_not_positive_definite() -> None:
    hip = _synthetic_hip(np.eye(3), mass=-np.eye(3))
    surface = SurfacePoint(np.array([0.0, 0.0, -R_HIP]), np.array([0.0, 0.0, 1.0]))
    with pytest.raises(InputError, match="mass_matrix"):
        ForceConstraint().rows(hip, surface, DT)


def test_fused_surface_like_objects_are_accepted(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.zeros(N))
    point = _surface_at(hip, [0, 0, 1], 0.0, velocity=[0, 0, 0.1])
    fused = SimpleNamespace(
        centroid=point.centroid, normal=point.normal, velocity=point.velocity, valid=True
    )
    for con in (PositionalConstraint(), VelocityConstraint(), ForceConstraint()):
        a, b = con.rows(hip, point, DT), con.rows(hip, fused, DT)
        np.testing.assert_array_equal(a.G, b.G)
        np.testing.assert_array_equal(a.h, b.h)


# ----- property tests: never NaN -----------------------------------------------------------------
finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)


@st.composite
def random_problems(draw):
    n = draw(st.integers(1, 7))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    kind = draw(st.sampled_from(["random", "zero", "rank1", "tiny", "huge"]))
    jac = rng.normal(size=(3, n))
    if kind == "zero":
        jac[:] = 0.0
    elif kind == "rank1":
        jac = np.outer(rng.normal(size=3), rng.normal(size=n))
    elif kind == "tiny":
        jac *= 1e-12
    elif kind == "huge":
        jac *= 1e6
    a = rng.normal(size=(n, n))
    mass = a @ a.T + draw(st.sampled_from([1e-6, 1e-2, 1.0])) * np.eye(n)
    hip = HipState(
        rng.uniform(-2, 2, 3),
        rng.uniform(-10, 10, n),
        jac,
        rng.uniform(-100, 100, 3),
        mass,
        rng.uniform(-100, 100, n),
        draw(st.floats(0.0, 0.2)),
    )
    normal = np.array([draw(finite), draw(finite), draw(finite)])
    if np.linalg.norm(normal) < 1e-6:
        normal = np.array([0.0, 0.0, 1.0])
    centroid = hip.position - draw(st.floats(-0.3, 0.3)) * normal / np.linalg.norm(normal)
    surface = SurfacePoint(
        centroid,
        normal,
        np.array([draw(finite), draw(finite), draw(finite)]),
        draw(st.sampled_from(["", *BODY_REGIONS])),
    )
    dt = draw(st.sampled_from([1e-6, 1.0 / 800.0, 0.01, 1.0]))
    return hip, surface, dt


@settings(max_examples=150, deadline=None)
@given(
    random_problems(),
    st.floats(1.0, 1000.0),
    st.floats(0.0, 0.2),
    st.booleans(),
)
def test_rows_are_finite_for_any_state(problem, gain, width, feedforward) -> None:
    hip, surface, dt = problem
    n = hip.n_joints
    constraints = (
        PositionalConstraint(
            PositionalConstraintConfig(
                kp=gain, activation_distance_m=2.0, surface_velocity_feedforward=feedforward
            )
        ),
        VelocityConstraint(
            VelocityConstraintConfig(
                kv=gain,
                d_width_m=width,
                activation_distance_m=2.0,
                surface_velocity_feedforward=feedforward,
            )
        ),
        ForceConstraint(ForceConstraintConfig(activation_distance_m=1.0)),
    )
    for con in constraints:
        rows = con.rows(hip, surface, dt)
        assert rows.G.shape == (1, 2 * n) and rows.h.shape == (1,)
        assert np.all(np.isfinite(rows.G)) and np.all(np.isfinite(rows.h))
    assert math.isfinite(contact_force_n(hip, surface, np.zeros(n)))


def test_a_shared_haptic_state_gives_the_same_rows(model: RobotModel) -> None:
    hip = _hip(model, model.q_home, np.full(N, 0.2))
    surface = _surface_at(hip, [0.1, -0.3, 1.0], 0.004, velocity=[0.0, 0.1, 0.2], region="neck")
    hs = haptic_state(hip, surface)
    for con in (PositionalConstraint(), VelocityConstraint(), ForceConstraint()):
        own, shared = con.rows(hip, surface, DT), con.rows(hip, surface, DT, haptic=hs)
        np.testing.assert_array_equal(own.G, shared.G)
        np.testing.assert_array_equal(own.h, shared.h)
        assert own.name == shared.name == con.name


def test_bad_state_or_surface_is_named() -> None:
    hip = _synthetic_hip(np.eye(3))
    good = SurfacePoint(np.zeros(3), np.array([0.0, 0.0, 1.0]))
    cases = [
        (hip, good._replace(centroid=np.array([np.nan, 0.0, 0.0])), "surface.centroid"),
        (hip, good._replace(normal=np.zeros(3)), "surface.normal"),
        (hip, good._replace(velocity=np.array([0.0, np.inf, 0.0])), "surface.velocity"),
        (hip._replace(qd=np.zeros(2)), good, "hip.qd"),
        (hip._replace(qd=np.array([0.0, np.nan, 0.0])), good, "hip.qd"),
        (hip._replace(jacobian=np.ones((2, 3))), good, "jacobian"),
        (hip._replace(position=np.array([0.0, 0.0, np.inf])), good, "hip.position"),
        (hip._replace(radius_m=-0.1), good, "hip.radius_m"),
        (hip._replace(radius_m=math.inf), good, "hip.radius_m"),
    ]
    for state, surface, name in cases:
        with pytest.raises(InputError, match=name):
            haptic_state(state, surface)
