"""The hierarchical solver: priorities, compromises, failures, and DAQP against the cascade."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest
from hapticloud.core.control import (
    Equality,
    HierarchicalController,
    HierarchicalSolver,
    HierarchyConfig,
    HipMotionTask,
    Inequality,
    SolveStatus,
    solve_cascade,
    solve_hierarchy,
)
from hapticloud.core.control import hierarchy as hierarchy_module
from hapticloud.core.control.controller import StepInputs
from hapticloud.core.errors import ConfigError, InputError
from hypothesis import given, settings
from hypothesis import strategies as st

# DAQP's soft levels are biased by ~rho_soft |x| (1e-7) and its hard rows drift when a lower
# level is badly violated; measured worst disagreement 1.1e-5 over 6600 random hierarchies
# (median ~1e-9), so the agreement bound is 2e-5 of max(1, |x|).
AGREE_RTOL = 2e-5


def _eq(rows: list[list[float]], b: list[float], name: str = "") -> Equality:
    return Equality(np.array(rows, dtype=float), np.array(b, dtype=float), name)


def _le(rows: list[list[float]], h: list[float], name: str = "") -> Inequality:
    return Inequality(np.array(rows, dtype=float), np.array(h, dtype=float), name)


def _agree(levels: list, n: int, metric: np.ndarray | None = None) -> None:
    got = HierarchicalSolver(n, metric=metric).solve(levels)
    ref = solve_cascade(levels, n, metric=metric)
    assert ref.ok
    assert np.isfinite(got.x).all()
    scale = max(1.0, float(np.abs(ref.x).max()))
    np.testing.assert_allclose(got.x, ref.x, rtol=0, atol=AGREE_RTOL * scale)
    np.testing.assert_allclose(
        got.level_slack, ref.level_slack, rtol=1e-4, atol=AGREE_RTOL * scale * 10
    )


# ----- semantics ----------------------------------------------------------------------------------
def test_lower_priority_task_is_sacrificed() -> None:
    top = [_le([[1.0]], [1.0], "x <= 1")]
    low = [_eq([[1.0]], [3.0], "x = 3")]
    res = HierarchicalSolver(1).solve([top, low])
    assert res.x[0] == pytest.approx(1.0, abs=1e-9)
    assert res.status is SolveStatus.RELAXED
    np.testing.assert_allclose(res.level_slack, [0.0, 2.0], atol=1e-7)
    assert res.level_satisfied.tolist() == [True, False]
    # The other order: the equality wins, the inequality is the one relaxed.
    res = HierarchicalSolver(1).solve([low, top])
    assert res.x[0] == pytest.approx(3.0, abs=1e-9)
    # The same report for any point.
    slack, holds = HierarchicalSolver(1).evaluate([top, low], [3.0])
    np.testing.assert_allclose(slack, [2.0, 0.0])
    assert holds.tolist() == [False, True]


def test_sacrifice_is_minimal_and_keeps_free_directions() -> None:
    # Level 1: x0 + x1 <= 1. Level 2: x = (2, 2). The least violation of level 2 is the
    # projection of (2, 2) on the half-plane: (0.5, 0.5).
    res = HierarchicalSolver(2).solve([[_le([[1, 1]], [1])], [_eq([[1, 0], [0, 1]], [2, 2])]])
    np.testing.assert_allclose(res.x, [0.5, 0.5], atol=1e-6)
    np.testing.assert_allclose(res.level_slack[1], np.sqrt(4.5), rtol=1e-6)


def test_same_level_conflict_is_the_least_squares_compromise() -> None:
    # x = 1 and x = 3 in one level -> 2; scaling a row does not change it (rows are normalised).
    for rows in ([[1.0], [1.0]], [[1.0], [10.0]]):
        b = [1.0, 3.0 * rows[1][0]]
        res = HierarchicalSolver(1).solve([[_eq(rows, b)]])
        assert res.x[0] == pytest.approx(2.0, abs=1e-6)
    # Two inequalities that cannot both hold at the same (non-top) level: x <= 0, x >= 1.
    res = HierarchicalSolver(1).solve([[], [_le([[1.0], [-1.0]], [0.0, -1.0])]])
    assert res.x[0] == pytest.approx(0.5, abs=1e-6)
    # Compromise of a 2-D level with a metric: distances in the metric decide.
    metric = np.array([1.0, 4.0])
    levels = [[_eq([[1, 0], [0, 1]], [1, 1])], [_eq([[1, 1]], [0])]]
    _agree(levels, 2, metric)


def test_infeasible_top_level_is_reported_with_the_best_compromise() -> None:
    top = [_le([[1.0], [-1.0]], [0.0, -1.0], "x <= 0 and x >= 1")]
    low = [_eq([[1.0]], [5.0])]
    res = HierarchicalSolver(1).solve([top, low])
    assert res.status is SolveStatus.TOP_LEVEL_INFEASIBLE
    assert res.solver == "daqp_soft"
    assert res.x[0] == pytest.approx(0.5, abs=1e-6)
    assert not res.level_satisfied[0]


def test_tikhonov_tie_break_is_the_metric_minimum_norm() -> None:
    # One equality in two variables: x0 + x1 = 1; with metric (1, 4) the minimum of
    # x0^2 + 4 x1^2 on the line is (0.8, 0.2).
    res = HierarchicalSolver(2, metric=[1.0, 4.0]).solve([[_eq([[1, 1]], [1])]])
    np.testing.assert_allclose(res.x, [0.8, 0.2], atol=1e-6)
    assert res.status is SolveStatus.OPTIMAL


def test_duplicate_and_dependent_rows_are_harmless() -> None:
    levels = [
        [_eq([[1, 0], [1, 0], [2, 0]], [1, 1, 2])],  # consistent duplicates in the hard level
        [_eq([[0, 1], [0, 1]], [2, 4]), _le([[0, -1], [0, -1]], [-5, -5])],
    ]
    res = HierarchicalSolver(2).solve(levels)
    assert res.status is SolveStatus.RELAXED
    _agree(levels, 2)


def test_zero_rows_are_reported_not_solved() -> None:
    levels = [
        [_eq([[1.0, 0.0]], [1.0])],
        [_le([[0.0, 0.0]], [-2.0], "0 <= -2")],
        [_eq([[0.0, 1.0]], [3.0])],
    ]
    res = HierarchicalSolver(2).solve(levels)
    np.testing.assert_allclose(res.x, [1.0, 3.0], atol=1e-9)
    np.testing.assert_allclose(res.level_slack, [0.0, 2.0, 0.0], atol=1e-9)
    assert res.level_satisfied.tolist() == [True, False, True]


def test_infinite_upper_bounds_are_inactive_rows() -> None:
    res = HierarchicalSolver(1).solve([[_le([[1.0]], [np.inf])], [_eq([[1.0]], [7.0])]])
    assert res.x[0] == pytest.approx(7.0) and res.status is SolveStatus.OPTIMAL


@pytest.mark.parametrize(
    "task",
    [
        _le([[np.nan]], [1.0]),
        _le([[1.0]], [np.nan]),
        _le([[1.0]], [-np.inf]),
        _eq([[1.0]], [np.inf]),
        _eq([[np.inf]], [1.0]),
    ],
)
def test_non_finite_rows_give_invalid_input_and_zero(task: Equality | Inequality) -> None:
    res = HierarchicalSolver(1).solve([[_eq([[1.0]], [1.0])], [task]])
    assert res.status is SolveStatus.INVALID_INPUT
    np.testing.assert_array_equal(res.x, [0.0])


def test_empty_hierarchies_and_levels() -> None:
    res = HierarchicalSolver(3).solve([])
    assert res.status is SolveStatus.OPTIMAL and res.x.shape == (3,)
    res = HierarchicalSolver(3).solve([[], [Inequality(np.zeros((0, 3)), np.zeros(0))], []])
    assert res.status is SolveStatus.OPTIMAL and res.level_slack.shape == (3,)
    res = HierarchicalSolver(1).solve([[], [], [_eq([[1.0]], [2.0])]])
    assert res.x[0] == pytest.approx(2.0)


def test_bad_arguments_raise_input_errors() -> None:
    solver = HierarchicalSolver(2)
    with pytest.raises(InputError, match="Equality or Inequality"):
        solver.solve([[(np.eye(2), np.zeros(2))]])
    with pytest.raises(InputError, match="shape"):
        solver.solve([[_eq([[1.0, 2.0, 3.0]], [1.0])]])
    with pytest.raises(InputError, match="shape"):
        solver.solve([[Equality(np.eye(2), np.zeros(3))]])
    with pytest.raises(InputError, match="metric"):
        HierarchicalSolver(2, metric=[1.0, -1.0])
    with pytest.raises(InputError, match="n_vars"):
        HierarchicalSolver(0)
    with pytest.raises(ConfigError, match="rho_soft"):
        HierarchyConfig(rho_soft=1.0)


def test_all_soft_mode_and_plain_lists() -> None:
    levels = [
        [Equality([[1.0, 1.0]], [2.0])],
        [Inequality([[1.0, 0.0]], [0.5])],
        [_eq([[1, 0], [0, 1]], [0, 0])],
    ]
    hard = HierarchicalSolver(2).solve(levels)
    soft = HierarchicalSolver(2, HierarchyConfig(hard_top_level=False)).solve(levels)
    assert hard.solver == "daqp" and soft.solver == "daqp_soft"
    np.testing.assert_allclose(hard.x, [0.5, 1.5], atol=1e-6)
    np.testing.assert_allclose(soft.x, hard.x, atol=1e-6)
    assert hard.status is soft.status is SolveStatus.RELAXED


def test_result_reports_timing_and_active_set() -> None:
    res = solve_hierarchy([[_le([[1.0, 0.0]], [1.0])], [_eq([[1.0, 0.0]], [3.0])]], 2)
    assert res.solve_us > 0 and res.iterations >= 1 and res.exitflag in (1, 2)
    assert res.active.shape == (2,) and res.active[0]


def test_daqp_failure_falls_back_to_the_cascade(monkeypatch: pytest.MonkeyPatch) -> None:
    def failing(*args: object, **kwargs: object) -> tuple:
        return np.full(2, np.nan), 0.0, -4, {"iterations": 10000, "lam": np.zeros(2)}

    monkeypatch.setattr(hierarchy_module.daqp, "solve", failing)
    levels = [[_le([[1.0, 1.0]], [1.0])], [_eq([[1, 0], [0, 1]], [2, 2])]]
    res = HierarchicalSolver(2).solve(levels)
    assert res.solver == "cascade" and res.status is SolveStatus.RELAXED
    np.testing.assert_allclose(res.x, [0.5, 0.5], atol=1e-6)
    res = HierarchicalSolver(2, HierarchyConfig(fallback="none")).solve(levels)
    assert res.status is SolveStatus.FAILED
    np.testing.assert_array_equal(res.x, [0.0, 0.0])


# ----- DAQP against the cascade -------------------------------------------------------------------
@st.composite
def hierarchies(draw: st.DrawFn) -> tuple[int, list, np.ndarray | None]:
    """Random hierarchies: Gaussian or grid-valued rows, duplicates, infeasible levels."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    n = draw(st.integers(1, 6))
    grid = draw(st.booleans())
    levels = []
    for _ in range(draw(st.integers(1, 5))):
        level = []
        for _ in range(draw(st.integers(0, 2))):
            m = draw(st.integers(0, 4))
            if grid:  # many exact ties and degenerate vertices
                A = np.round(rng.uniform(-3, 3, size=(m, n)) * 2) / 2
                b = np.round(rng.uniform(-5, 5, size=m) * 2) / 2
            else:
                A = rng.normal(size=(m, n)) * 10 ** rng.uniform(-1, 1)
                b = rng.normal(size=m) * 3
            if m > 1 and draw(st.booleans()):  # a duplicate (scaled) row, maybe conflicting
                A[-1] = A[0] * rng.choice([1.0, -1.0, 2.0])
            kind = Equality if draw(st.booleans()) else Inequality
            level.append(kind(A, b, "random"))
        levels.append(level)
    metric = np.exp(rng.uniform(-1, 1, size=n)) if draw(st.booleans()) else None
    return n, levels, metric


@settings(max_examples=150, derandomize=True, deadline=None)
@given(hierarchies())
def test_daqp_agrees_with_the_cascade_on_random_hierarchies(problem: tuple) -> None:
    n, levels, metric = problem
    _agree(levels, n, metric)


def _manipulator_problems(count: int) -> list[tuple[list, np.ndarray]]:
    model = pin.buildSampleModelManipulator()
    data = model.createData()
    n = model.nv
    frame = model.nframes - 1
    ctrl = HierarchicalController(
        None,
        n,
        np.full(n, -2.0),
        np.full(n, 2.0),
        np.full(n, 2.0),
        np.array([80, 80, 40, 20, 10, 10.0]),
        wall_points=[[0, 0, 0.3]],
        wall_normals=[[0, 0, 1]],
    )
    rng = np.random.default_rng(11)
    out = []
    for _ in range(count):
        q = rng.uniform(-2.3, 2.3, size=n)  # sometimes beyond the limits
        qd = rng.normal(size=n) * rng.choice([0.1, 1.0, 5.0])
        pin.computeAllTerms(model, data, q, qd)
        M = np.triu(data.M) + np.triu(data.M, 1).T
        J = pin.getFrameJacobian(model, data, frame, pin.LOCAL_WORLD_ALIGNED)[:3]
        p = data.oMf[frame].translation.copy()
        jd = pin.getFrameClassicalAcceleration(model, data, frame, pin.LOCAL_WORLD_ALIGNED).linear
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        G = np.concatenate([-(normal @ J), np.zeros(n)])[None, :]
        haptic = [
            Inequality(G, np.array([rng.normal() * 50]), "positional"),
            Inequality(G * rng.uniform(0.5, 2), np.array([rng.normal() * 20]), "velocity"),
        ]
        motion = None
        if rng.random() < 0.5:
            motion = HipMotionTask(n).rows(p, J, jd, qd, p + rng.normal(size=3) * 0.2)
        levels = ctrl._levels(
            StepInputs(q, qd, M, data.nle.copy(), 1 / 800, p, J, jd, haptic, [], motion, None)
        )
        out.append((levels, ctrl.solver.metric))
    return out


def test_daqp_agrees_with_the_cascade_on_controller_hierarchies() -> None:
    for levels, metric in _manipulator_problems(25):
        _agree(levels, metric.size, np.asarray(metric))
