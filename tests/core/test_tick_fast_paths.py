"""The 800 Hz tick's fast paths give exactly what the checked, general code gives.

Stacked rows (controller) against the row objects stacked by the solver; the robot model's
per-tick checks against list inputs and non-finite values; the fusion's reuse of a held
surface's arrays; the loop on a robot other than the shipped model (the public step)."""

from __future__ import annotations

import inspect
import math

import numpy as np
import pinocchio as pin
import pytest
from hapticloud.core.control import (
    ControllerConfig,
    Equality,
    HierarchicalController,
    Inequality,
)
from hapticloud.core.control.controller import StepInputs
from hapticloud.core.control.hierarchy import StackedLevels
from hapticloud.core.control.reductions import finite_total
from hapticloud.core.errors import InputError
from hapticloud.core.fusion import FusionConfig, SurfaceFusion
from hapticloud.core.loop import (
    TANGENT_BAND_M_S2,
    HapticLoop,
    HapticsConfig,
    Wall,
    _tangents,
    build_controller,
)
from hapticloud.core.perception.estimate import SurfaceEstimate
from hapticloud.core.robot import RobotModel
from hypothesis import given
from hypothesis import strategies as st

DT = 1.0 / 800.0


@pytest.fixture(scope="module")
def robot() -> RobotModel:
    return RobotModel.load()


def _state(robot: RobotModel, seed: int) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    q = robot.q_home + rng.normal(scale=0.2, size=robot.n_joints)
    qd = rng.normal(scale=1.0, size=robot.n_joints)
    robot.update(q, qd)
    return (
        robot.q,
        robot.qd,
        robot.mass_matrix(),
        robot.nonlinear_effects(),
        robot.hip_position(),
        robot.hip_jacobian(),
        robot.hip_jdot_qd(),
    )


@pytest.mark.parametrize("level", ["dynamics", "safety"])
@pytest.mark.parametrize("seed", range(4))
def test_stacked_rows_are_the_stacked_row_objects(robot: RobotModel, level: str, seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    cfg = ControllerConfig(torque_limit_level=level).with_overrides(
        {"min_acceleration.damping_1_per_s": float(seed % 2)}
    )
    q, qd, M, h, p, J, jd = _state(robot, seed)
    ctrl = HierarchicalController.from_robot(
        robot, cfg, wall_points=[p - [0, 0, 0.1]], wall_normals=[[0.0, 0.0, 1.0]]
    )
    n = robot.n_joints
    haptic = [Inequality(rng.normal(size=(k, 2 * n)), rng.normal(size=k), "h") for k in (1, 0, 3)]
    extra = [Inequality(rng.normal(size=(2, 2 * n)), rng.normal(size=2), "w")]
    motion = None if seed % 2 else Equality(rng.normal(size=(3, 2 * n)), rng.normal(size=3), "m")
    tau_int = None if seed == 3 else rng.normal(size=n)
    for _ in range(2):  # twice: the buffers' second use must not see the first's rows
        args = StepInputs(q, qd, M, h, DT, p, J, jd, haptic, extra, motion, tau_int)
        stacked = ctrl._stacked(args)
        A, bu, bl, counts = ctrl.solver._stack(ctrl._levels(args))
        assert isinstance(stacked, StackedLevels)
        assert stacked.counts == counts
        np.testing.assert_array_equal(stacked.A, A)
        np.testing.assert_array_equal(stacked.bu, bu)
        np.testing.assert_array_equal(stacked.bl, bl)
        assert len(stacked) == len(counts) and len(list(stacked)) == len(counts)


def test_step_results_match_the_row_object_solve(robot: RobotModel) -> None:
    q, qd, M, h, _, J, _ = _state(robot, 7)
    ctrl = HierarchicalController.from_robot(robot)
    n = robot.n_joints
    G = np.concatenate([-np.array([0.0, 0.0, 1.0]) @ J, np.zeros(n)])[None, :]
    rows = [Inequality(G, np.array([-5.0]), "haptic")]
    out = ctrl.step(q, qd, M, h, DT, haptic_rows=rows)
    levels = ctrl._levels(StepInputs(q, qd, M, h, DT, None, None, None, rows, [], None, None))
    ref = ctrl.solver.solve(levels)
    np.testing.assert_array_equal(out.qdd, ref.x[:n])
    assert out.status.value == ("ok" if ref.level_satisfied[1:5].all() else "relaxed")


def test_step_checks_the_rows_it_is_handed(robot: RobotModel) -> None:
    q, qd, M, h, *_ = _state(robot, 1)
    ctrl = HierarchicalController.from_robot(robot)
    n = robot.n_joints
    with pytest.raises(InputError, match="level 4"):
        ctrl.step(q, qd, M, h, DT, haptic_rows=[Inequality(np.zeros((1, n)), np.zeros(1))])
    with pytest.raises(InputError, match="Equality or Inequality"):
        ctrl.step(q, qd, M, h, DT, wall_rows=[np.zeros((1, 2 * n))])  # type: ignore[list-item]
    with pytest.raises(InputError, match="real numbers"):
        bad = Inequality(np.full((1, 2 * n), "x"), np.zeros(1))
        ctrl.step(q, qd, M, h, DT, haptic_rows=[bad])
    with pytest.raises(InputError, match="interaction_torque"):
        ctrl.step(q, qd, M, h, DT, interaction_torque=np.zeros(n + 1))
    nan_row = Inequality(np.full((1, 2 * n), np.nan), np.zeros(1), "nan_row")
    out = ctrl.step(q, qd, M, h, DT, haptic_rows=[nan_row])
    assert out.status.value == "fault" and "nan_row" in out.fault


def test_huge_finite_bounds_are_not_invalid(robot: RobotModel) -> None:
    # Squares of 1e200 overflow; the finiteness check must then look at the sum itself.
    q, qd, M, h, *_ = _state(robot, 2)
    ctrl = HierarchicalController.from_robot(robot)
    n = robot.n_joints
    row = Inequality(np.eye(1, 2 * n), np.array([1e200]), "far")
    out = ctrl.step(q, qd, M, h, DT, haptic_rows=[row])
    assert out.status.value == "ok"


def test_model_update_fast_path_matches_list_inputs(robot: RobotModel) -> None:
    rng = np.random.default_rng(3)
    q = robot.q_home + rng.normal(scale=0.1, size=robot.n_joints)
    qd = rng.normal(size=robot.n_joints)
    robot.update(q.tolist(), qd.tolist())
    ref = [a.copy() for a in (robot.hip_position(), robot.hip_jacobian(), robot.mass_matrix())]
    ref.append(robot.nonlinear_effects().copy())
    robot.update(q, qd)
    got = (
        robot.hip_position(),
        robot.hip_jacobian(),
        robot.mass_matrix(),
        robot.nonlinear_effects(),
    )
    for a, b in zip(ref, got, strict=True):
        np.testing.assert_array_equal(a, b)
        assert not b.flags.writeable
    np.testing.assert_array_equal(robot.mass_matrix(), robot.mass_matrix().T)
    np.testing.assert_array_equal(robot.hip_velocity(), robot.hip_jacobian() @ qd)
    data = robot.pin_model.createData()
    np.testing.assert_allclose(robot.mass_matrix(), pin.crba(robot.pin_model, data, q), atol=0)
    q[0] += 1.0  # the model keeps its own copy
    assert robot.q[0] != q[0]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("which", ["q", "qd"])
def test_model_update_rejects_non_finite(robot: RobotModel, bad: float, which: str) -> None:
    q = robot.q_home.copy()
    qd = np.zeros(robot.n_joints)
    (q if which == "q" else qd)[2] = bad
    with pytest.raises(InputError, match=f"^{which}: must be finite"):
        robot.update(q, qd)
    # One good vector and one zero: a product q . qd would hide nothing (inf * 0 is NaN).
    with pytest.raises(InputError, match="must be finite"):
        robot.update(q if which == "q" else robot.q_home, qd if which == "qd" else np.zeros(6))


def test_model_accepts_finite_vectors_whose_sum_overflows(robot: RobotModel) -> None:
    big = np.zeros(robot.n_joints)
    big[0] = big[1] = 1e308  # their sum overflows
    assert robot._joint_vector(big, "tau") is big


def test_fusion_held_surface_reuses_equal_read_only_arrays() -> None:
    cfg = FusionConfig()
    fusion = SurfaceFusion(cfg)
    fusion.add(SurfaceEstimate(0.0, "cam0", (0.1, 0.0, 0.5), (0.0, 0.0, 1.0), True))
    fusion.add(SurfaceEstimate(0.03, "cam0", (0.1, 0.01, 0.5), (0.0, 0.1, 0.995), True))
    t = 0.03 + cfg.max_age_s + 0.01
    outs = [fusion.sample(t + k * DT) for k in range(3)]
    assert all(o.stale and not o.valid for o in outs)
    fresh = SurfaceFusion(cfg)
    fresh.add(SurfaceEstimate(0.0, "cam0", (0.1, 0.0, 0.5), (0.0, 0.0, 1.0), True))
    fresh.add(SurfaceEstimate(0.03, "cam0", (0.1, 0.01, 0.5), (0.0, 0.1, 0.995), True))
    ref = [fresh.sample(t + k * DT) for k in range(3)]
    for a, b in zip(outs, ref, strict=True):
        for name in ("centroid", "normal", "velocity", "target_centroid", "target_normal"):
            va, vb = getattr(a, name), getattr(b, name)
            np.testing.assert_array_equal(va, vb)
            assert va.shape == (3,) and not va.flags.writeable
        assert a.reason == b.reason


class _OtherRobot:
    """The shipped model behind another type: the loop must take the controller's public step."""

    def __init__(self, model: RobotModel) -> None:
        self._m = model

    def __getattr__(self, name: str) -> object:
        return getattr(self._m, name)


def test_loop_on_another_robot_type_gives_the_same_tick(robot: RobotModel) -> None:
    q = robot.q_home
    hip = robot.hip_position_at(q)
    wall = Wall.make("floor", hip - [0.0, 0.0, 0.04 + 0.001], [0.0, 0.0, 1.0], part="hand")
    qd = np.array([0.0, 0.0, 0.3, 0.0, 0.2, 0.0])
    outs = []
    for r in (robot, _OtherRobot(robot)):
        ctrl = build_controller(r, None, [wall])
        loop = HapticLoop(
            r, ctrl, HapticsConfig(exact_shortcut=False), hip_radius_m=0.04, dt=DT, walls=[wall]
        )
        assert loop._trusted is (r is robot)
        outs.append(loop.tick(0.0, q, qd, interaction_torque=np.zeros(6)))
    a, b = outs
    np.testing.assert_array_equal(a.tau, b.tau)
    np.testing.assert_array_equal(a.qdd, b.qdd)
    assert (a.status, a.rows, a.clamped) == (b.status, b.rows, b.clamped)
    assert a.rows  # the wall is within reach: rows were built and solved


def test_tangential_rows_match_the_array_expressions(robot: RobotModel) -> None:
    _, _, _, _, _, J, _ = _state(robot, 4)
    ctrl = build_controller(robot, None, [])
    loop = HapticLoop(robot, ctrl, hip_radius_m=0.04, dt=DT)
    n = robot.n_joints
    rng = np.random.default_rng(8)
    for _ in range(20):
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        qdd5 = rng.normal(size=n)
        m = loop._tangential_rows(J, [normal], qdd5, 1)
        assert m == 5
        gs = _tangents(normal).dot(J)
        a = gs.dot(qdd5)
        np.testing.assert_array_equal(loop._G[1:5, :n], np.concatenate([gs, -gs]))
        np.testing.assert_array_equal(
            loop._h[1:5], np.concatenate([a + TANGENT_BAND_M_S2, TANGENT_BAND_M_S2 - a])
        )


@given(
    st.lists(
        st.one_of(
            st.none(),
            st.lists(
                st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([1e200, -1e308]),
                max_size=6,
            ),
        ),
        max_size=4,
    )
)
def test_finite_total_is_whether_the_plain_sum_is_finite(parts) -> None:
    arrays = tuple(None if p is None else np.array(p, dtype=np.float64) for p in parts)
    with np.errstate(over="ignore", invalid="ignore"):
        plain = sum(float(np.sum(a)) for a in arrays if a is not None)
        assert finite_total(arrays) == math.isfinite(plain)


# ----- each formula once: the rows and the tick's fast path call the same kernel --------------
def _count_calls(monkeypatch: pytest.MonkeyPatch, owner: object, name: str) -> list[int]:
    """Wrap ``owner.name`` to count its calls (still returning what it returns)."""
    calls = [0]
    original = getattr(owner, name)

    def counted(*args, **kwargs):
        calls[0] += 1
        return original(*args, **kwargs)

    static = isinstance(inspect.getattr_static(owner, name), staticmethod)
    monkeypatch.setattr(owner, name, staticmethod(counted) if static else counted)
    return calls


@pytest.mark.parametrize(
    ("cls_path", "name"),
    [
        ("hapticloud.core.haptics.positional.PositionalConstraint", "bound"),
        ("hapticloud.core.haptics.velocity.VelocityConstraint", "bound"),
        ("hapticloud.core.haptics.force.ForceConstraint", "bound"),
    ],
)
def test_rows_and_tick_share_the_constraint_kernel(
    robot: RobotModel, monkeypatch: pytest.MonkeyPatch, cls_path: str, name: str
) -> None:
    import importlib

    from hapticloud.core.haptics import (
        ForceConstraint,
        HipState,
        PositionalConstraint,
        SurfacePoint,
        VelocityConstraint,
    )

    module_name, cls_name = cls_path.rsplit(".", 1)
    cls = getattr(importlib.import_module(module_name), cls_name)
    q, qd = robot.q_home, np.array([0.1, -0.2, 0.4, 0.1, -0.3, 0.2])
    hip = robot.hip_position_at(q)
    wall = Wall.make("floor", hip - [0.0, 0.0, 0.04 + 0.003], [0.0, 0.0, 1.0], part="hand")
    loop = HapticLoop(
        robot,
        build_controller(robot, None, [wall]),
        HapticsConfig(clearance_m=0.0),
        hip_radius_m=0.04,
        dt=DT,
        walls=[wall],
    )
    calls = _count_calls(monkeypatch, cls, name)
    loop.tick(0.0, q, qd)
    assert calls[0] == 1  # the tick's row came from the kernel
    robot.update(q, qd)
    state = HipState.from_model(robot, 0.04)
    surface = SurfacePoint(wall.point, wall.normal, np.zeros(3), "hand")
    constraint = {
        "PositionalConstraint": PositionalConstraint,
        "VelocityConstraint": VelocityConstraint,
        "ForceConstraint": ForceConstraint,
    }[cls_name]()
    rows = constraint.rows(state, surface, DT)
    assert calls[0] == 2  # and so did the row object's
    assert rows.h.shape == (1,)


def test_velocity_cap_uses_the_velocity_kernel(robot: RobotModel) -> None:
    """The held surface's cap is the velocity row with v_c replaced by the cap: the same kernel."""
    from hapticloud.core.haptics import HipState, SurfacePoint, VelocityConstraint, haptic_state

    q, qd = robot.q_home, np.array([0.1, -0.2, 0.4, 0.1, -0.3, 0.2])
    hip = robot.hip_position_at(q)
    wall = Wall.make("floor", hip - [0.0, 0.0, 0.04 + 0.003], [0.0, 0.0, 1.0], part="hand")
    cfg = HapticsConfig(clearance_m=0.0, positional_enabled=False)
    loop = HapticLoop(
        robot, build_controller(robot, None, [wall]), cfg, hip_radius_m=0.04, dt=DT, walls=[wall]
    )
    loop.approach_limit_mps = 0.01  # tighter than v_min: the cap sets the row
    loop.tick(0.0, q, qd)
    robot.update(q, qd)
    hs = haptic_state(
        HipState.from_model(robot, 0.04), SurfacePoint(wall.point, wall.normal, np.zeros(3))
    )
    expected = VelocityConstraint(cfg.velocity).bound(hs, DT, 0.01)
    assert loop._h[0] == expected


@pytest.mark.parametrize("seed", range(4))
def test_joint_limit_check_is_the_rows_inequality(robot: RobotModel, seed: int) -> None:
    """The shortcut's per-joint test and the limit tasks' rows accept the same x (away from the
    tolerance band), and the stacked rows are the tasks' own bounds."""
    rng = np.random.default_rng(seed)
    ctrl = build_controller(robot, None, [])
    check = ctrl.limit_check(DT, 0.0)
    n = robot.n_joints
    seen = set()
    for _ in range(200):
        q = rng.uniform(robot.q_min, robot.q_max)
        qd = rng.normal(0, 1.0, n)
        qdd = rng.normal(0, 200.0, n)
        tau = rng.normal(0, 1.0, n) * robot.tau_max
        x = np.concatenate([qdd, tau])
        rows = [
            ctrl.position_limit.rows(q, qd, DT),
            ctrl.velocity_limit.rows(qd, DT),
            ctrl.torque_limit.rows(),
        ]
        margins = np.concatenate([r.h - r.G @ x for r in rows])
        if np.min(np.abs(margins)) < 1e-6:
            continue  # within rounding of a bound: the two forms may round differently
        held = bool(np.all(margins >= 0.0))
        assert check.admits(tau.tolist(), q.tolist(), qd.tolist(), qdd.tolist()) is held
        seen.add(held)
    assert seen == {True, False}  # both outcomes were tested
