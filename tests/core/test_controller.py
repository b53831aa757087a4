"""The hierarchical controller: priorities, dynamics, torque limits, faults, closed loop, speed."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
import pytest
from hapticloud.core.control import (
    LEVEL_NAMES,
    ControllerConfig,
    ControlStatus,
    Equality,
    HierarchicalController,
    HipMotionTask,
    Inequality,
    JointMotionTask,
    SolveStatus,
)
from hapticloud.core.errors import ConfigError, InputError
from hypothesis import given, settings
from hypothesis import strategies as st

DT = 1.0 / 800.0
TAU_MAX = np.array([80.0, 80.0, 40.0, 20.0, 10.0, 10.0])
Q0 = np.array([0.1, -0.6, 1.2, 0.1, 0.4, 0.0])


@dataclass
class Arm:
    """The sample manipulator of Pinocchio as a stand-in for the exoskeleton (6 joints)."""

    model: pin.Model
    data: pin.Data
    frame: int

    @classmethod
    def build(cls) -> Arm:
        model = pin.buildSampleModelManipulator()
        return cls(model, model.createData(), model.nframes - 1)

    @property
    def n(self) -> int:
        return self.model.nv

    def state(self, q: np.ndarray, qd: np.ndarray) -> dict[str, np.ndarray]:
        """What a control tick needs: dynamics and the HIP (last frame) kinematics."""
        m, d, f = self.model, self.data, self.frame
        pin.computeAllTerms(m, d, q, qd)
        jac = pin.getFrameJacobian(m, d, f, pin.LOCAL_WORLD_ALIGNED)[:3].copy()
        return {
            "mass_matrix": np.triu(d.M) + np.triu(d.M, 1).T,
            "nonlinear_effects": d.nle.copy(),
            "hip_position": d.oMf[f].translation.copy(),
            "hip_jacobian": jac,
            "hip_jdot_qd": pin.getFrameClassicalAcceleration(
                m, d, f, pin.LOCAL_WORLD_ALIGNED
            ).linear.copy(),
        }

    def advance(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray, tau_ext: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """One semi-implicit Euler step of the true dynamics (ABA)."""
        qdd = pin.aba(self.model, self.data, q, qd, tau + tau_ext)
        qd = qd + DT * qdd
        return pin.integrate(self.model, q, DT * qd), qd


@pytest.fixture(scope="module")
def arm() -> Arm:
    return Arm.build()


def _controller(
    n: int = 6, config: ControllerConfig | None = None, **walls: object
) -> HierarchicalController:
    return HierarchicalController(
        config, n, np.full(n, -2.8), np.full(n, 2.8), np.full(n, 3.0), TAU_MAX[:n], **walls
    )


def _step(ctrl: HierarchicalController, arm: Arm, q: np.ndarray, qd: np.ndarray, **extra: object):
    s = arm.state(q, qd)
    hip = {k: s[k] for k in ("hip_position", "hip_jacobian", "hip_jdot_qd")}
    return ctrl.step(q, qd, s["mass_matrix"], s["nonlinear_effects"], DT, **hip, **extra), s


# ----- behaviour ----------------------------------------------------------------------------------
def test_free_space_gives_the_model_compensation_torque(arm: Arm) -> None:
    out, s = _step(_controller(), arm, Q0, np.zeros(6))
    assert out.status is ControlStatus.OK and not out.clamped
    np.testing.assert_allclose(out.tau, s["nonlinear_effects"], atol=1e-9)
    np.testing.assert_allclose(out.qdd, 0.0, atol=1e-9)
    assert out.level_slack.shape == (len(LEVEL_NAMES),)
    assert out.solve_us > 0 and out.step_us >= out.solve_us and out.fault == ""


def test_wall_outranks_the_motion_task(arm: Arm) -> None:
    s = arm.state(Q0, np.zeros(6))
    p = s["hip_position"]
    wall_z = p[2] - 0.045  # 5 mm of free distance with the default 0.04 m margin
    ctrl = _controller(wall_points=[[0, 0, wall_z]], wall_normals=[[0, 0, 1]])
    motion = HipMotionTask(6).rows(
        p, s["hip_jacobian"], s["hip_jdot_qd"], np.zeros(6), p - [0, 0, 0.2]
    )
    out, _ = _step(ctrl, arm, Q0, np.zeros(6), motion=motion)
    assert out.status is ControlStatus.RELAXED
    assert out.level_slack[2] < 1e-6  # the wall holds ...
    assert out.level_slack[4] > 1.0  # ... the motion task gives way
    hip_acc = s["hip_jacobian"] @ out.qdd + s["hip_jdot_qd"]
    T = ctrl.config.walls.horizon_s
    assert 0.005 + T * T / 2 * hip_acc[2] >= -1e-9  # predicted distance stays non-negative
    assert hip_acc[2] < 0  # still moving towards the wall as far as it allows


def test_haptic_rows_rank_below_walls_and_above_motion(arm: Arm) -> None:
    s = arm.state(Q0, np.zeros(6))
    p, J = s["hip_position"], s["hip_jacobian"]
    ctrl = _controller(wall_points=[[0, 0, p[2] - 0.045]], wall_normals=[[0, 0, 1]])
    # A haptic row demanding a downward HIP acceleration of at least 5 m/s^2 (into the wall).
    down = Inequality(np.concatenate([J[2], np.zeros(6)])[None, :], np.array([-5.0]), "push")
    motion = JointMotionTask(6).rows(Q0, np.zeros(6), Q0)  # "stay": conflicts with the push
    out, _ = _step(ctrl, arm, Q0, np.zeros(6), haptic_rows=[down], motion=motion)
    assert out.level_slack[2] < 1e-6 and out.level_slack[3] > 0.0
    # Without the wall, the haptic row is met and the motion task gives way.
    out, _ = _step(_controller(), arm, Q0, np.zeros(6), haptic_rows=[down], motion=motion)
    assert out.level_slack[3] < 1e-6 and out.level_slack[4] > 0.0
    assert (J @ out.qdd)[2] <= -5.0 + 1e-6


def test_joint_limit_brakes_within_the_torque_limits(arm: Arm) -> None:
    ctrl = _controller()
    T = ctrl.config.position_limit.horizon_s
    q, qd = Q0.copy(), np.zeros(6)
    q[2], qd[2] = 2.75, 2.75  # 0.05 rad below the upper limit, moving into it
    out, s = _step(ctrl, arm, q, qd)
    bound = 2.0 * (2.8 - q[2] - T * qd[2]) / T**2  # -25 rad/s^2: reachable
    assert out.qdd[2] <= bound + 1e-6
    assert out.level_slack[1] < 1e-6 and out.level_slack[4] > 0.0  # qdd = 0 gives way
    q[2], qd[2] = 2.79, 3.0  # now it cannot stop in time: brake as hard as the drive allows
    out, s = _step(ctrl, arm, q, qd)
    assert out.status is ControlStatus.RELAXED and out.level_slack[1] > 0.0
    assert out.qdd[2] < -40.0
    assert np.all(np.abs(out.tau) <= TAU_MAX) and abs(out.tau[2]) == pytest.approx(TAU_MAX[2])
    residual = s["mass_matrix"] @ out.qdd + s["nonlinear_effects"] - out.tau
    assert np.abs(residual).max() < 1e-8


def test_torque_limits_at_the_safety_level_are_clamped(arm: Arm) -> None:
    q = Q0.copy()
    q[1] = 2.78
    qd = np.zeros(6)
    qd[1] = 3.0  # stopping this needs far more than 80 N m
    for level, expect_clamp in (("dynamics", False), ("safety", True)):
        ctrl = _controller(config=ControllerConfig(torque_limit_level=level))
        out, s = _step(ctrl, arm, q, qd)
        assert out.clamped is expect_clamp
        assert np.all(np.abs(out.tau) <= TAU_MAX)
        # qdd is the model's answer to the torque actually sent, clamped or not.
        residual = s["mass_matrix"] @ out.qdd + s["nonlinear_effects"] - out.tau
        assert np.abs(residual).max() < 1e-8
        assert out.status is ControlStatus.RELAXED


def test_measured_interaction_torque_enters_the_dynamics(arm: Arm) -> None:
    s = arm.state(Q0, np.zeros(6))
    push = s["hip_jacobian"].T @ np.array([0.0, 0.0, -5.0])
    out, _ = _step(_controller(), arm, Q0, np.zeros(6), interaction_torque=push)
    # Minimising accelerations now cancels the measured push as well.
    np.testing.assert_allclose(out.tau, s["nonlinear_effects"] - push, atol=1e-9)


# ----- properties ---------------------------------------------------------------------------------
@settings(max_examples=60, derandomize=True, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    speed=st.sampled_from([0.0, 1.0, 10.0, 100.0]),
    force=st.sampled_from([0.0, 10.0, 1e3, 1e6]),
    level=st.sampled_from(["dynamics", "safety"]),
)
def test_torques_always_within_limits_and_dynamics_exact(
    arm: Arm, seed: int, speed: float, force: float, level: str
) -> None:
    rng = np.random.default_rng(seed)
    q = rng.uniform(-3.5, 3.5, size=6)  # sometimes far beyond the joint limits
    qd = rng.normal(size=6) * speed
    ctrl = _controller(
        config=ControllerConfig(torque_limit_level=level),
        wall_points=[[0, 0, 0.5]],
        wall_normals=[[0, 0, 1]],
    )
    s = arm.state(q, qd)
    normal = rng.normal(size=3)
    row = np.concatenate([-(normal @ s["hip_jacobian"]), np.zeros(6)])[None, :]
    haptic = [Inequality(row, rng.normal(size=1) * force, "haptic")]
    tau_int = s["hip_jacobian"].T @ (rng.normal(size=3) * force)
    out = ctrl.step(
        q,
        qd,
        s["mass_matrix"],
        s["nonlinear_effects"],
        DT,
        hip_position=s["hip_position"],
        hip_jacobian=s["hip_jacobian"],
        hip_jdot_qd=s["hip_jdot_qd"],
        haptic_rows=haptic,
        interaction_torque=tau_int,
    )
    assert out.status in (ControlStatus.OK, ControlStatus.RELAXED)
    assert np.isfinite(out.tau).all() and np.isfinite(out.qdd).all()
    assert np.all(np.abs(out.tau) <= TAU_MAX)
    residual = s["mass_matrix"] @ out.qdd + s["nonlinear_effects"] - tau_int - out.tau
    assert np.abs(residual).max() < 1e-8 * (1.0 + np.abs(tau_int).max())


# ----- faults -------------------------------------------------------------------------------------
def _nan_cases() -> list[tuple[str, str]]:
    return [
        ("q", "q"),
        ("qd", "qd"),
        ("mass_matrix", "mass_matrix"),
        ("nonlinear_effects", "nonlinear_effects"),
        ("dt", "dt"),
        ("hip_position", "hip_position"),
        ("hip_jacobian", "hip_jacobian"),
        ("hip_jdot_qd", "hip_jdot_qd"),
        ("interaction_torque", "interaction_torque"),
        ("haptic_rows", "haptic"),
        ("motion", "motion"),
    ]


@pytest.mark.parametrize(("field", "named"), _nan_cases())
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_inputs_give_zero_torque_and_a_fault(
    arm: Arm, field: str, named: str, bad: float
) -> None:
    s = arm.state(Q0, np.zeros(6))
    args = {
        "q": Q0.copy(),
        "qd": np.zeros(6),
        "dt": DT,
        **{k: v.copy() for k, v in s.items()},
        "interaction_torque": np.zeros(6),
        "haptic_rows": [Inequality(np.ones((1, 12)), np.array([1.0]), "haptic")],
        "motion": Equality(np.eye(6, 12), np.zeros(6), "motion"),
    }
    if field == "dt":
        args["dt"] = bad
    elif field == "haptic_rows":
        args["haptic_rows"] = [Inequality(np.full((1, 12), bad), np.array([1.0]), "haptic")]
    elif field == "motion":
        args["motion"] = Equality(np.eye(6, 12), np.full(6, bad), "motion")
    else:
        args[field] = np.array(args[field], dtype=float)
        args[field].flat[0] = bad
    ctrl = _controller(wall_points=[[0, 0, 0.0]], wall_normals=[[0, 0, 1]])
    out = ctrl.step(
        args.pop("q"),
        args.pop("qd"),
        args.pop("mass_matrix"),
        args.pop("nonlinear_effects"),
        args.pop("dt"),
        **args,
    )
    assert out.status is ControlStatus.FAULT
    np.testing.assert_array_equal(out.tau, 0.0)
    assert np.isfinite(out.qdd).all()
    assert named in out.fault


def test_solver_failure_holds_the_compensation_torque(
    arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    ctrl = _controller()
    real = ctrl.solver.solve
    monkeypatch.setattr(
        ctrl.solver, "solve", lambda levels: real(levels)._replace(status=SolveStatus.FAILED)
    )
    big = np.array([500.0, -500.0, 0.0, 0.0, 0.0, 0.0])
    s = arm.state(Q0, np.zeros(6))
    out = ctrl.step(Q0, np.zeros(6), s["mass_matrix"], big, DT)
    assert out.status is ControlStatus.SOLVER_FAILED and "failed" in out.fault
    np.testing.assert_allclose(out.tau, np.clip(big, -TAU_MAX, TAU_MAX))
    assert out.clamped


def test_programming_errors_raise(arm: Arm) -> None:
    s = arm.state(Q0, np.zeros(6))
    walled = _controller(wall_points=[[0, 0, 0.0]], wall_normals=[[0, 0, 1]])
    with pytest.raises(InputError, match="hip_position"):
        walled.step(Q0, np.zeros(6), s["mass_matrix"], s["nonlinear_effects"], DT)
    with pytest.raises(InputError, match="mass_matrix"):
        _controller().step(Q0, np.zeros(6), np.eye(5), s["nonlinear_effects"], DT)
    with pytest.raises(InputError, match="dt"):
        _controller().step(Q0, np.zeros(6), s["mass_matrix"], s["nonlinear_effects"], 0.0)
    with pytest.raises(InputError, match="tau_max"):
        HierarchicalController(None, 2, [-1, -1], [1, 1], [1, 1], [1.0])
    with pytest.raises(InputError, match="wall_points"):
        _controller(wall_points=[[0, 0, 0.0]])


def test_config_tables_and_errors_name_the_field() -> None:
    cfg = ControllerConfig.from_dict({"walls": {"margin_m": 0.05}, "solver": {"rho_soft": 1e-8}})
    assert cfg.walls.margin_m == 0.05 and cfg.solver.rho_soft == 1e-8
    assert ControllerConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ConfigError, match=r"walls\.margin_m"):
        ControllerConfig.from_dict({"walls": {"margin_m": -1.0}})
    with pytest.raises(ConfigError, match="torque_limit_level"):
        ControllerConfig(torque_limit_level="sometimes")


# ----- closed loop --------------------------------------------------------------------------------
def test_closed_loop_wall_stops_the_motion_task_softly(arm: Arm) -> None:
    wall_z = arm.state(Q0, np.zeros(6))["hip_position"][2] - 0.1
    ctrl = _controller(wall_points=[[0, 0, wall_z]], wall_normals=[[0, 0, 1]])
    task = HipMotionTask(6)
    q, qd = Q0.copy(), np.zeros(6)
    distances = []
    for _ in range(400):  # 0.5 s
        s = arm.state(q, qd)
        p = s["hip_position"]
        motion = task.rows(p, s["hip_jacobian"], s["hip_jdot_qd"], qd, [p[0], p[1], wall_z - 0.1])
        out, _ = _step(ctrl, arm, q, qd, motion=motion)
        assert out.status in (ControlStatus.OK, ControlStatus.RELAXED)
        q, qd = arm.advance(q, qd, out.tau, np.zeros(6))
        distances.append(p[2] - wall_z - ctrl.config.walls.margin_m)
    # The prediction acts as a spring-damper (damping ratio 1/sqrt(2)): a small overshoot into
    # the margin, then it rests on the wall.
    assert min(distances) > -0.005
    assert abs(distances[-1]) < 1e-4


def test_closed_loop_unmodelled_push_bounces_off_the_wall(arm: Arm) -> None:
    wall_z = arm.state(Q0, np.zeros(6))["hip_position"][2] - 0.1
    ctrl = _controller(wall_points=[[0, 0, wall_z]], wall_normals=[[0, 0, 1]])
    q, qd = Q0.copy(), np.zeros(6)
    distances = []
    for _ in range(400):
        out, s = _step(ctrl, arm, q, qd)
        push = s["hip_jacobian"].T @ np.array([0.0, 0.0, -10.0])  # the patient, not modelled
        q, qd = arm.advance(q, qd, out.tau, push)
        distances.append(s["hip_position"][2] - wall_z - ctrl.config.walls.margin_m)
    assert min(distances) > -0.01  # stopped within the 0.04 m margin
    assert max(distances[-100:]) > min(distances)  # and pushed back out (the paper's rebound)


# ----- speed (benchmark, not run by default) ------------------------------------------------------
@pytest.mark.slow
def test_benchmark_step_time(arm: Arm) -> None:
    """10,000 closed-loop steps with walls, two haptic rows and a motion task; prints µs."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    wall_z = arm.state(Q0, np.zeros(6))["hip_position"][2] - 0.1
    ctrl = _controller(wall_points=[[0, 0, wall_z]], wall_normals=[[0, 0, 1]])
    task = HipMotionTask(6)
    rng = np.random.default_rng(0)
    q, qd = Q0.copy(), np.zeros(6)
    steps, solves, statuses = [], [], {}
    for k in range(10_000):
        s = arm.state(q, qd)
        p, J = s["hip_position"], s["hip_jacobian"]
        target = p + 0.05 * np.array([np.sin(k / 400), np.cos(k / 300), -1.0])
        motion = task.rows(p, J, s["hip_jdot_qd"], qd, target)
        normal = np.array([0.0, np.sin(k / 500), np.cos(k / 500)])
        Jc = np.concatenate([-(normal @ J), np.zeros(6)])[None, :]
        haptic = [
            Inequality(Jc, np.array([20.0 + rng.normal()]), "positional"),
            Inequality(0.5 * Jc, np.array([5.0]), "velocity"),
        ]
        out, _ = _step(ctrl, arm, q, qd, haptic_rows=haptic, motion=motion)
        steps.append(out.step_us)
        solves.append(out.solve_us)
        statuses[out.status.value] = statuses.get(out.status.value, 0) + 1
        push = J.T @ (rng.normal(size=3) * 2.0)
        q, qd = arm.advance(q, qd, out.tau, push)
    steps_arr, solves_arr = np.array(steps), np.array(solves)
    print()
    for name, arr in (("step", steps_arr), ("solve", solves_arr)):
        print(f"{name} median {np.median(arr):.1f} us  p99 {np.percentile(arr, 99):.1f} us")
    print(f"statuses {statuses}")
    assert np.median(steps_arr) < 1000.0
