"""Each controller task's rows: shapes, signs (the allowed side is feasible) and edge cases."""

from __future__ import annotations

import numpy as np
import pytest
from hapticloud.core.control import (
    Equality,
    EquationOfMotion,
    EquationOfMotionConfig,
    FixedWalls,
    FixedWallsConfig,
    HipMotionConfig,
    HipMotionTask,
    Inequality,
    JointMotionConfig,
    JointMotionTask,
    JointPositionLimit,
    JointPositionLimitConfig,
    JointVelocityLimit,
    JointVelocityLimitConfig,
    MinimizeAcceleration,
    MinimizeAccelerationConfig,
    TorqueLimit,
    TorqueLimitConfig,
)
from hapticloud.core.errors import ConfigError, InputError

N = 6
DT = 1.0 / 800.0


def _spd(rng: np.random.Generator, n: int = N) -> np.ndarray:
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def _holds(rows: Inequality, x: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    return rows.G @ x <= rows.h + tol * (1.0 + np.abs(rows.h))


# ----- equation of motion -------------------------------------------------------------------------
def test_equation_of_motion_rows_hold_exactly_for_the_dynamics() -> None:
    rng = np.random.default_rng(0)
    M, h, qdd = _spd(rng), rng.normal(size=N), rng.normal(size=N)
    rows = EquationOfMotion(N).rows(M, h)
    assert isinstance(rows, Equality) and rows.name == "equation_of_motion"
    assert rows.A.shape == (N, 2 * N) and rows.b.shape == (N,)
    x = np.concatenate([qdd, M @ qdd + h])
    np.testing.assert_allclose(rows.A @ x, rows.b, atol=1e-12)


def test_equation_of_motion_interaction_torque_is_scaled() -> None:
    rng = np.random.default_rng(1)
    M, h, tau_int, qdd = _spd(rng), rng.normal(size=N), rng.normal(size=N), rng.normal(size=N)
    half = EquationOfMotion(N, EquationOfMotionConfig(interaction_torque_scale=0.5))
    rows = half.rows(M, h, tau_int)
    # M qdd + h = tau + 0.5 tau_int
    x = np.concatenate([qdd, M @ qdd + h - 0.5 * tau_int])
    np.testing.assert_allclose(rows.A @ x, rows.b, atol=1e-12)


def test_equation_of_motion_checks_shapes() -> None:
    eom = EquationOfMotion(N)
    with pytest.raises(InputError, match="mass_matrix"):
        eom.rows(np.eye(N - 1), np.zeros(N))
    with pytest.raises(InputError, match="nonlinear_effects"):
        eom.rows(np.eye(N), np.zeros(N + 1))
    with pytest.raises(InputError, match="n_joints"):
        EquationOfMotion(0)


# ----- joint limits -------------------------------------------------------------------------------
def test_position_limit_bound_is_the_predicted_limit() -> None:
    q_min, q_max = -np.ones(N), np.ones(N)
    task = JointPositionLimit(q_min, q_max, JointPositionLimitConfig(horizon_s=0.02))
    q = np.linspace(-0.9, 0.9, N)
    qd = np.linspace(2.0, -2.0, N)
    rows = task.rows(q, qd, DT)
    assert rows.G.shape == (2 * N, 2 * N) and rows.h.shape == (2 * N,)
    T = 0.02
    # The largest allowed acceleration puts the prediction exactly on the upper limit.
    qdd_up = rows.h[:N]
    np.testing.assert_allclose(q + T * qd + T * T / 2 * qdd_up, q_max, atol=1e-12)
    qdd_lo = -rows.h[N:]
    np.testing.assert_allclose(q + T * qd + T * T / 2 * qdd_lo, q_min, atol=1e-12)
    # Inside: zero acceleration is feasible when the prediction stays inside.
    assert _holds(task.rows(np.zeros(N), np.zeros(N), DT), np.zeros(2 * N)).all()


def test_position_limit_rejects_acceleration_into_the_limit() -> None:
    task = JointPositionLimit(-np.ones(N), np.ones(N))
    q = np.full(N, 0.99)
    qd = np.full(N, 1.0)  # moving into the upper limit
    rows = task.rows(q, qd, DT)
    coast = np.zeros(2 * N)
    assert not _holds(rows, coast)[:N].any()  # coasting crosses the limit within the horizon
    brake = np.concatenate([np.full(N, -1e4), np.zeros(N)])
    assert _holds(rows, brake).all()


def test_position_limit_margin_and_horizon_floor() -> None:
    cfg = JointPositionLimitConfig(horizon_s=0.0, margin_rad=0.1)
    task = JointPositionLimit(-np.ones(N), np.ones(N), cfg)
    assert task.horizon_s(DT) == DT  # never shorter than one period
    rows = task.rows(np.zeros(N), np.zeros(N), DT)
    np.testing.assert_allclose(DT * DT / 2 * rows.h[:N], 0.9, rtol=1e-12)


def test_position_limit_infinite_bounds_are_inactive_never_nan() -> None:
    q_min = np.array([-np.inf, -1, -1, -1, -1, -1.0])
    q_max = np.array([np.inf, 1, 1, 1, 1, 1.0])
    rows = JointPositionLimit(q_min, q_max).rows(np.zeros(N), np.ones(N), DT)
    assert not np.isnan(rows.h).any()
    assert rows.h[0] == np.inf and rows.h[N] == np.inf


def test_position_limit_rejects_crossed_limits() -> None:
    with pytest.raises(InputError, match="q_min, q_max"):
        JointPositionLimit(np.ones(N), -np.ones(N))
    with pytest.raises(InputError, match="q_max"):
        JointPositionLimit(-np.ones(N), np.full(N, np.nan))


def test_velocity_limit_bound_is_the_limit_after_the_horizon() -> None:
    v_max = np.full(N, 2.0)
    task = JointVelocityLimit(v_max, JointVelocityLimitConfig(horizon_s=0.01))
    qd = np.linspace(-1.5, 1.5, N)
    rows = task.rows(qd, DT)
    np.testing.assert_allclose(qd + 0.01 * rows.h[:N], v_max, atol=1e-12)
    np.testing.assert_allclose(qd - 0.01 * rows.h[N:], -v_max, atol=1e-12)
    assert _holds(rows, np.zeros(2 * N)).all()
    with pytest.raises(InputError, match="v_max"):
        JointVelocityLimit(np.zeros(N))


def test_torque_limit_rows_are_constant_and_read_only() -> None:
    tau_max = np.arange(1.0, N + 1)
    task = TorqueLimit(tau_max, TorqueLimitConfig(scale=0.5))
    rows = task.rows()
    assert rows is task.rows()
    assert not rows.G.flags.writeable and not rows.h.flags.writeable
    inside = np.concatenate([np.zeros(N), 0.5 * tau_max])
    outside = np.concatenate([np.zeros(N), 0.51 * tau_max])
    assert _holds(rows, inside).all() and _holds(rows, -inside).all()
    assert not _holds(rows, outside)[:N].any()
    with pytest.raises(InputError, match="tau_max"):
        TorqueLimit(np.full(N, np.inf))
    with pytest.raises(ConfigError, match="scale"):
        TorqueLimitConfig(scale=0.0)


# ----- fixed walls --------------------------------------------------------------------------------
def test_wall_row_keeps_the_predicted_distance_non_negative() -> None:
    rng = np.random.default_rng(2)
    cfg = FixedWallsConfig(horizon_s=0.02, margin_m=0.04, activation_distance_m=1.0)
    walls = FixedWalls([[0, 0, 0]], [[0, 0, 2.0]], N, cfg)  # normal is normalised
    p = np.array([0.1, 0.2, 0.1])
    J = rng.normal(size=(3, N))
    jdqd = rng.normal(size=3)
    qd = rng.normal(size=N)
    rows = walls.rows(p, J, jdqd, qd, DT)
    assert rows.G.shape == (1, 2 * N) and rows.name == "fixed_walls"
    np.testing.assert_allclose(walls.distances(p), [0.06])
    T = 0.02

    def predicted_distance(qdd: np.ndarray) -> float:
        vel = J @ qd
        acc = J @ qdd + jdqd
        return 0.06 + T * vel[2] + T * T / 2 * acc[2]

    # A qdd on the row's boundary predicts exactly zero distance; the allowed side is positive.
    g = rows.G[0, :N]
    qdd_edge = g * (rows.h[0] / (g @ g))
    assert predicted_distance(qdd_edge) == pytest.approx(0.0, abs=1e-12)
    into = qdd_edge + 10.0 * g / np.linalg.norm(g)  # more of -n^T J qdd: towards the wall
    away = qdd_edge - 10.0 * g / np.linalg.norm(g)
    assert predicted_distance(into) < 0 and not _holds(rows, np.concatenate([into, np.zeros(N)]))[0]
    assert predicted_distance(away) > 0 and _holds(rows, np.concatenate([away, np.zeros(N)]))[0]


def test_walls_beyond_the_activation_distance_give_no_row() -> None:
    cfg = FixedWallsConfig(activation_distance_m=0.3, margin_m=0.0)
    walls = FixedWalls([[0, 0, 0], [0, 0, 2.0]], [[0, 0, 1], [0, 0, -1]], N, cfg)
    assert walls.n_walls == 2
    J, z3 = np.ones((3, N)), np.zeros(3)
    rows = walls.rows([0, 0, 0.2], J, z3, np.zeros(N), DT)
    assert rows.G.shape == (1, 2 * N)
    rows = walls.rows([0, 0, 1.0], J, z3, np.zeros(N), DT)
    assert rows.G.shape == (0, 2 * N) and rows.h.shape == (0,)


def test_walls_validate_their_geometry() -> None:
    with pytest.raises(InputError, match=r"normals\[0\]"):
        FixedWalls([[0, 0, 0]], [[0, 0, 0]], N)
    with pytest.raises(InputError, match="points, normals"):
        FixedWalls([[0, 0, 0]], [[0, 0, 1], [0, 1, 0]], N)
    walls = FixedWalls([[0, 0, 0]], [[0, 0, 1]], N)
    with pytest.raises(InputError, match="hip_jacobian"):
        walls.rows(np.zeros(3), np.zeros((3, N + 1)), np.zeros(3), np.zeros(N), DT)
    with pytest.raises(InputError, match="dt"):
        walls.rows(np.zeros(3), np.zeros((3, N)), np.zeros(3), np.zeros(N), 0.0)


# ----- level 5 ------------------------------------------------------------------------------------
def test_minimize_acceleration_rows() -> None:
    rows = MinimizeAcceleration(N).rows()
    assert rows.A.shape == (N, 2 * N)
    np.testing.assert_array_equal(rows.A[:, :N], np.eye(N))
    np.testing.assert_array_equal(rows.b, 0.0)
    damped = MinimizeAcceleration(N, MinimizeAccelerationConfig(damping_1_per_s=4.0))
    np.testing.assert_allclose(damped.rows(np.ones(N)).b, -4.0)
    with pytest.raises(InputError, match="qd"):
        damped.rows()


def test_joint_motion_pd_and_saturation() -> None:
    cfg = JointMotionConfig(
        stiffness_1_per_s2=100, damping_1_per_s=20, max_acceleration_rad_per_s2=1e3
    )
    task = JointMotionTask(N, cfg)
    q = np.zeros(N)
    rows = task.rows(q, np.zeros(N), q)
    np.testing.assert_array_equal(rows.b, 0.0)  # at rest on target: no acceleration
    rows = task.rows(q, np.zeros(N), np.full(N, 0.1))
    np.testing.assert_allclose(rows.b, 10.0)  # towards the target
    rows = task.rows(q, np.ones(N), q, qd_target=np.ones(N), qdd_target=np.full(N, 2.0))
    np.testing.assert_allclose(rows.b, 2.0)
    small = JointMotionTask(N, JointMotionConfig(max_acceleration_rad_per_s2=1.0))
    b = small.rows(q, np.zeros(N), np.full(N, 5.0)).b
    assert np.linalg.norm(b) == pytest.approx(1.0) and (b > 0).all()


def test_hip_motion_rows_track_the_target() -> None:
    rng = np.random.default_rng(3)
    J = rng.normal(size=(3, N))
    jdqd = rng.normal(size=3)
    qd = rng.normal(size=N)
    task = HipMotionTask(
        N, HipMotionConfig(stiffness_1_per_s2=50, damping_1_per_s=10, max_acceleration_m_per_s2=1e3)
    )
    p = np.array([0.3, 0.0, 0.5])
    target = p + np.array([0.01, 0.0, 0.0])
    rows = task.rows(p, J, jdqd, qd, target)
    assert rows.A.shape == (3, 2 * N)
    # A qdd meeting the rows gives the commanded HIP acceleration J qdd + Jdot qd.
    qdd = np.linalg.lstsq(rows.A[:, :N], rows.b, rcond=None)[0]
    expected = 50 * (target - p) + 10 * (0 - J @ qd)
    np.testing.assert_allclose(J @ qdd + jdqd, expected, atol=1e-9)


def test_stage_configs_validate_with_field_names() -> None:
    with pytest.raises(ConfigError, match="horizon_s"):
        JointPositionLimitConfig(horizon_s=-0.1)
    with pytest.raises(ConfigError, match="margin_m"):
        FixedWallsConfig(margin_m=2.0)
    with pytest.raises(ConfigError, match="damping_1_per_s"):
        MinimizeAccelerationConfig(damping_1_per_s=-1.0)
