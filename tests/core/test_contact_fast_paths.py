"""The hierarchy solver's per-layout cache gives exactly what working the layout out each call
gives: break points, report segments, and results when layouts change, rows appear or vanish,
levels empty, and inputs are NaN (the same flagged result)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hapticloud.core.control import Equality, HierarchicalSolver, Inequality
from hapticloud.core.control.hierarchy import SolveStatus, _layout


def _levels(rng: np.random.Generator, counts: list[int], n: int = 4) -> list[list]:
    """One task per level, equalities and inequalities alternating, ``counts`` rows each."""
    kinds = itertools.cycle((Inequality, Equality))
    return [[next(kinds)(rng.normal(size=(c, n)), rng.normal(size=c), "t")] for c in counts]


def _same(a: object, b: object) -> None:
    for x, y in zip(a, b, strict=True):  # type: ignore[call-overload]
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape
            np.testing.assert_array_equal(x, y)
        elif not isinstance(x, float):  # solve_us is a timing
            assert x == y


LAYOUTS = [[3, 2, 1], [3, 0, 2, 0], [3, 2, 1], [0, 2, 2], [1], [3, 2, 1, 4], [3, 2, 1]]


def test_layout_parts_are_what_the_counts_imply() -> None:
    for counts in LAYOUTS:
        lay = _layout(counts)
        ends = list(itertools.accumulate(counts))
        assert lay.hard_points.tolist() == ends and lay.soft_points.tolist() == [0, *ends]
        assert lay.hard_points.dtype == np.intc == lay.soft_points.dtype
        nonempty = [k for k, c in enumerate(counts) if c]
        assert lay.nonempty.tolist() == nonempty
        assert lay.starts.tolist() == [([0, *ends])[k] for k in nonempty]


def test_cached_layouts_give_the_fresh_solver_results_as_layouts_change() -> None:
    # One solver sees layouts change, recur, rows appear and vanish; a fresh solver per problem
    # (empty cache) is the reference.
    rng = np.random.default_rng(5)
    kept = HierarchicalSolver(4)
    for counts in LAYOUTS * 2:
        levels = _levels(rng, counts)
        _same(kept.solve(levels), HierarchicalSolver(4).solve(levels))
        x = rng.normal(size=4)
        _same(kept.evaluate(levels, x), HierarchicalSolver(4).evaluate(levels, x))
    assert set(kept._layouts) == {tuple(c) for c in LAYOUTS}


def test_daqp_leaves_the_cached_break_points_alone() -> None:
    rng = np.random.default_rng(6)
    solver = HierarchicalSolver(4)
    for _ in range(20):
        solver.solve(_levels(rng, [2, 3, 4]))
        # An infeasible hard top level: the soft retry uses the other array.
        solver.solve([[Equality(np.ones((2, 4)), np.array([0.0, 1.0]), "clash")], []])
    assert solver._layouts[(2, 3, 4)].hard_points.tolist() == [2, 5, 9]
    assert solver._layouts[(2, 3, 4)].soft_points.tolist() == [0, 2, 5, 9]
    assert solver._layouts[(2, 0)].soft_points.tolist() == [0, 2, 2]


def test_the_cache_stops_growing_but_keeps_solving() -> None:
    rng = np.random.default_rng(7)
    solver = HierarchicalSolver(4)
    for k in range(70):
        levels = _levels(rng, [1, 1 + k % 35, 2 * (k // 35)])
        _same(solver.solve(levels), HierarchicalSolver(4).solve(levels))
    assert len(solver._layouts) == 64


@pytest.mark.parametrize("bad", [np.nan, -np.inf])
def test_non_finite_rows_are_flagged_as_before_with_a_cached_layout(bad: float) -> None:
    rng = np.random.default_rng(8)
    solver = HierarchicalSolver(4)
    levels = _levels(rng, [3, 2, 1])
    assert solver.solve(levels).status is not SolveStatus.INVALID_INPUT
    levels[1][0][1][0] = bad
    res = solver.solve(levels)
    assert res.status is SolveStatus.INVALID_INPUT
    _same(res, HierarchicalSolver(4).solve(levels))
    np.testing.assert_array_equal(res.x, np.zeros(4))


def test_closed_loop_solves_match_a_solver_with_an_empty_cache(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Every hierarchy solve of a contact run against the same rows solved by a fresh solver.
    from hapticloud.core.scene import load_scene
    from hapticloud.core.sim.closed_loop import ClosedLoopSim

    loaded = load_scene("impacts", None)
    loaded = loaded.with_overrides({f"cameras.{c.name}.model": "oracle" for c in loaded.cameras})
    compared = []
    solve = HierarchicalSolver.solve

    def checked(self: HierarchicalSolver, levels):  # type: ignore[no-untyped-def]
        stacked = (levels.A.copy(), levels.bu.copy(), levels.bl.copy(), list(levels.counts))
        res = solve(self, levels)
        fresh = HierarchicalSolver(self.n_vars, self.config, metric=self.metric)
        ref = solve(fresh, type(levels)(*stacked, levels._build))
        _same(res, ref)
        compared.append(res.status)
        return res

    monkeypatch.setattr(HierarchicalSolver, "solve", checked)
    ClosedLoopSim(loaded).run(1.5)
    assert len(compared) > 100
