"""Hierarchical least squares with inequalities, solved in one call by DAQP's hierarchical mode.

A hierarchy is a list of levels in priority order; a level is a list of tasks
(:class:`~.rows.Equality` ``A x = b`` or :class:`~.rows.Inequality` ``G x <= h``). Each level is
solved in the optimal set of the levels above it:

- level ``k`` minimises ``sum_i (r_i / nu_i)^2`` over its rows, ``r_i`` the row's violation and
  ``nu_i = |a_i|_{H^-1}`` the row's length in the metric ``H = diag(metric)``. DAQP normalises
  every row to unit length internally, so a compromise inside a level is measured as distances in
  ``x``-space: scaling a row (or a whole task) does not change it. Priorities, not weights, rank
  tasks here.
- the optimal set of a level keeps its equalities at their optimal residual and its
  inequalities relaxed by their optimal slack; the final ``x`` is the ``H``-minimum-norm point
  of the last optimal set (the Tikhonov tie-break, which makes the lowest level well-posed).

How DAQP is driven (daqp 0.11; every statement below was checked on small problems):

- ``daqp.solve(H, f, A, bupper, blower, sense, break_points, ...)`` with ``break_points`` the
  cumulative row ends of the levels. Equalities are rows with ``blower == bupper``; inequalities
  have ``blower = -1e30`` (DAQP's infinity). ``H`` must be given: it is the Tikhonov metric.
- DAQP keeps its *first* level hard: it is solved exactly (the equation of motion then holds to
  ~1e-15) or the solve fails: exit flag -1 with a single level, 3 ("the LDP of a level failed,
  x is the point before it") with several, -6 for conflicting dependent equalities. Every later
  level is soft: DAQP adds a slack weighted ``1/rho_soft`` to each row, solves, shifts the bounds
  of the rows that needed slack by that slack and hardens the level. A leading break point of 0
  makes every level soft; that is the retry after any failure of the hard solve, so an
  infeasible top level still gets the least-squares compromise of all levels. Only exit flags 1
  and 2 are accepted. In this mode ``info["lam"]`` holds slacks, not multipliers.
- ``rho_soft`` is the Tikhonov weight inside each level: slacks come out biased by about
  ``rho_soft * |x|``; the multipliers of soft rows are ``slack / rho_soft``, and when those are
  large (a lower level badly violated) even the hard first level drifts (up to 2e-4 N m on the
  equation of motion at 1e-7, in extreme controller states). Measured against the cascade on
  3000 Gaussian, 3000 grid-valued and 600 extreme controller hierarchies, 1e-7 disagreed by more
  than 1e-6 (relative) in 1, 1 and 3 of them (at most 1.1e-5; median ~1e-9); 1e-8 in 0, 1, 37
  (at most 1e-3); 1e-6 in 8, 11, 2; 1e-9 and below by up to 0.87 (hard rows drifting). Callers
  that need their top level exact polish it (the controller recomputes ``tau = M qdd + h``).
- rows of zero length cannot be normalised (DAQP would divide by zero); they are handed to DAQP
  as inactive rows and only counted in the report.

When DAQP fails (cycling, iteration limit, a non-finite answer) the level-by-level quadprog
cascade of :mod:`.cascade` is tried; when that fails too, ``x`` is zero with status ``FAILED``.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple

import daqp
import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..config import StageConfig, param
from ..errors import ConfigError, InputError
from .cascade import solve_cascade
from .reductions import and_reduce, finite_total, min_reduce
from .rows import Equality, Inequality, task_parts

FloatArray = NDArray[np.float64]

#: DAQP's "infinite" bound: rows with a bound at or beyond it are never active on that side.
DAQP_INF = 1e30
# 1 optimal, 2 optimal with some soft constraint relaxed. daqp 0.11 returns 3 when the LDP of
# some level failed (x is then the point before that level): not an answer to accept.
_EXIT_SUCCESS = (1, 2)

Task = Equality | Inequality


class SolveStatus(StrEnum):
    """Outcome of a hierarchy solve."""

    #: every row of every level holds.
    OPTIMAL = "optimal"
    #: the top level holds; some lower level was sacrificed (normal when tasks conflict).
    RELAXED = "relaxed"
    #: the top level itself cannot hold; ``x`` is the least-squares compromise of all levels.
    TOP_LEVEL_INFEASIBLE = "top_level_infeasible"
    #: no solver produced an answer; ``x`` is zero.
    FAILED = "failed"
    #: a row held NaN or -inf (or an equality +inf); ``x`` is zero.
    INVALID_INPUT = "invalid_input"


@dataclass(frozen=True)
class HierarchyConfig(StageConfig):
    """Parameters of the hierarchical solver."""

    hard_top_level: bool = param(
        True, doc="solve the first level as hard constraints (exact); soft retry if infeasible"
    )
    rho_soft: float = param(
        1e-7,
        lo=1e-12,
        hi=1e-4,
        log_scale=True,
        doc="DAQP soft-constraint weight: Tikhonov weight inside a level (slack bias ~ rho |x|)",
    )
    primal_tol: float = param(
        1e-9, lo=1e-12, hi=1e-4, log_scale=True, doc="DAQP primal feasibility tolerance"
    )
    iter_limit: int = param(1000, lo=10, hi=100000, doc="DAQP active-set iteration limit")
    feasibility_tol: float = param(
        1e-7,
        lo=1e-12,
        hi=1e-2,
        log_scale=True,
        doc="a row holds when its violation < tol * (|a_i| + |b_i|) (status and report)",
    )
    zero_row_tol: float = param(
        1e-10,
        lo=0.0,
        hi=1e-3,
        log_scale=False,
        doc="rows shorter than this (in the metric) are rows of zeros: reported, not solved",
    )
    fallback: str = param(
        "cascade",
        choices=("cascade", "none"),
        doc="what to try when DAQP fails: the quadprog cascade, or nothing (x = 0)",
    )


class HierarchyResult(NamedTuple):
    """What :meth:`HierarchicalSolver.solve` returns.

    Attributes
    ----------
    x
        Solution, shape ``(n_vars,)``; never NaN (zero when no answer was found).
    status
        :class:`SolveStatus`.
    level_slack
        Euclidean norm of each level's violations, rows in their own units, shape ``(p,)``.
    level_satisfied
        Whether every row of each level holds within ``feasibility_tol`` at the returned ``x``.
        A hard top level DAQP accepted counts as holding for ``status`` even when rounding
        drift (see the module notes) makes this False.
    active
        Rows at (or beyond) their bound at ``x``, over the stacked rows (levels in order, tasks
        in order); every equality is active. (DAQP's hierarchical mode returns slacks, not
        multipliers, so the working set is read from ``x``.)
    solver
        ``"daqp"`` (hard top level), ``"daqp_soft"`` (all levels soft), ``"cascade"`` or ``""``.
    exitflag
        DAQP's exit flag of the last DAQP call (``> 0`` success).
    iterations
        DAQP's active-set iterations, summed over levels.
    solve_us
        Wall time of the whole call (assembly, DAQP, report), microseconds.
    """

    x: FloatArray
    status: SolveStatus
    level_slack: FloatArray
    level_satisfied: NDArray[np.bool_]
    active: NDArray[np.bool_]
    solver: str
    exitflag: int
    iterations: int
    solve_us: float


class _Layout(NamedTuple):
    """What the rows per level imply, worked out once per layout (a few recur tick after tick)."""

    #: DAQP's break points with the first level hard, and with a leading 0 (every level soft).
    hard_points: NDArray[np.intc]
    soft_points: NDArray[np.intc]
    #: The levels with rows and the index of their first row (``reduceat`` needs both).
    nonempty: NDArray[np.intp]
    starts: NDArray[np.intp]


def _layout(counts: Sequence[int]) -> _Layout:
    ends = list(itertools.accumulate(counts))
    nonempty = [k for k, c in enumerate(counts) if c]
    starts = [0, *ends]
    return _Layout(
        np.array(ends, dtype=np.intc),
        np.array([0, *ends], dtype=np.intc),
        np.array(nonempty, dtype=np.intp),
        np.array([starts[k] for k in nonempty], dtype=np.intp),
    )


class StackedLevels(Sequence[Sequence[Task]]):
    """A hierarchy its builder has already stacked into DAQP's arrays (private to the package).

    :meth:`HierarchicalSolver.solve` takes ``A``, ``bu``, ``bl`` and ``counts`` as they are, as
    :meth:`HierarchicalSolver._stack` would have built them, so a controller that keeps its
    constant rows in a buffer skips re-stacking ~60 rows of row objects every tick. As a sequence
    it is the list of levels (built by ``build`` on first use only: the fallback cascade and
    callers that inspect the levels need it, the DAQP path does not).

    The solver bounds ``bu`` at DAQP's infinity in place; the builder rewrites it every tick.
    """

    __slots__ = ("A", "_build", "_levels", "bl", "bu", "counts")

    def __init__(
        self,
        A: FloatArray,
        bu: FloatArray,
        bl: FloatArray,
        counts: list[int],
        build: Callable[[], Sequence[Sequence[Task]]],
    ) -> None:
        self.A, self.bu, self.bl, self.counts = A, bu, bl, counts
        self._build = build
        self._levels: Sequence[Sequence[Task]] | None = None

    def levels(self) -> Sequence[Sequence[Task]]:
        """The levels as lists of row objects (built once)."""
        if self._levels is None:
            self._levels = self._build()
        return self._levels

    def __len__(self) -> int:
        return len(self.counts)

    def __getitem__(self, index):  # type: ignore[no-untyped-def, override]
        return self.levels()[index]

    def __iter__(self) -> Iterator[Sequence[Task]]:
        return iter(self.levels())


class HierarchicalSolver:
    """Solve task hierarchies over ``n_vars`` decision variables with DAQP's hierarchical mode.

    Parameters
    ----------
    n_vars
        Number of decision variables (``2 * n_joints`` for ``x = [qdd; tau]``).
    config
        :class:`HierarchyConfig`; defaults when omitted.
    metric
        Diagonal of ``H`` (positive, finite): the Tikhonov tie-break ``min |x|_H`` and the metric
        in which rows are normalised. Ones by default.
    capacity
        Rows of DAQP's constraint-type buffer pre-allocated (it grows when needed).

    Examples
    --------
    >>> import numpy as np
    >>> from hapticloud.core.control import Equality, Inequality, HierarchicalSolver
    >>> solver = HierarchicalSolver(1)
    >>> top = [Inequality(np.array([[1.0]]), np.array([1.0]), "x <= 1")]
    >>> low = [Equality(np.array([[1.0]]), np.array([3.0]), "x = 3")]
    >>> result = solver.solve([top, low])
    >>> round(float(result.x[0]), 9), result.status.value
    (1.0, 'relaxed')
    """

    def __init__(
        self,
        n_vars: int,
        config: HierarchyConfig | None = None,
        *,
        metric: ArrayLike | None = None,
        capacity: int = 64,
    ) -> None:
        if isinstance(n_vars, bool) or not isinstance(n_vars, int | np.integer) or n_vars < 1:
            raise InputError(f"n_vars = {n_vars!r}: expected a positive integer")
        self.n_vars = int(n_vars)
        self.config = config if config is not None else HierarchyConfig()
        if not isinstance(self.config, HierarchyConfig):
            raise ConfigError(f"config: expected HierarchyConfig, got {type(config).__name__}")
        w = np.ones(self.n_vars) if metric is None else np.asarray(metric, dtype=np.float64)
        w = w.reshape(-1)
        if w.shape != (self.n_vars,) or not np.all(np.isfinite(w)) or not np.all(w > 0):
            raise InputError(f"metric: expected {self.n_vars} positive finite numbers")
        self.metric = w.copy()
        self.metric.setflags(write=False)
        self._H = np.ascontiguousarray(np.diag(w))
        self._f = np.zeros(self.n_vars)
        self._inv_metric = 1.0 / w
        self._settings = {
            "rho_soft": self.config.rho_soft,
            "primal_tol": self.config.primal_tol,
            "iter_limit": self.config.iter_limit,
        }
        self._sense = np.zeros(max(int(capacity), 1), dtype=np.intc)
        self._minus_inf = np.full(max(int(capacity), 1), -DAQP_INF)
        self._minus_inf.setflags(write=False)
        self._layouts: dict[tuple[int, ...], _Layout] = {}

    # ----- assembly -------------------------------------------------------------------------------
    def _stack(
        self, levels: Sequence[Sequence[Task]]
    ) -> tuple[FloatArray, FloatArray, FloatArray, list[int]]:
        """Stack every row: ``A``, upper and lower bounds (DAQP's form), rows per level."""
        n = self.n_vars
        mats: list[NDArray] = []
        uppers: list[NDArray] = []
        lowers: list[NDArray] = []
        counts: list[int] = []
        for k, level in enumerate(levels):
            count = 0
            for task in level:
                mat, vec, eq = self.task_arrays(task, k)
                rows = vec.shape[0]
                if rows:
                    mats.append(mat)
                    uppers.append(vec)
                    lowers.append(vec if eq else self._no_lower(rows))
                    count += rows
            counts.append(count)
        if not mats:
            empty = np.zeros(0)
            return np.zeros((0, n)), empty, empty, counts
        try:
            A = np.concatenate(mats, dtype=np.float64)
            bu = np.concatenate(uppers, dtype=np.float64)
            bl = np.concatenate(lowers, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError("task rows: expected real numbers") from None
        return A, bu, bl, counts

    def task_arrays(self, task: Task, k: int) -> tuple[NDArray, NDArray, bool]:
        """``task``'s matrix, right-hand side and whether it is an equality, shapes checked.

        ``k`` is the level's index (0 = top), for the message.
        """
        mat, vec, eq = task_parts(task, f"level {k + 1}")
        if not (isinstance(mat, np.ndarray) and isinstance(vec, np.ndarray)):
            mat, vec = self._as_arrays(mat, vec, task[2])
        n = self.n_vars
        if mat.ndim != 2 or mat.shape[1] != n or vec.shape != (mat.shape[0],):
            raise InputError(
                f"task {task[2]!r} (level {k + 1}): expected rows of shape (m, {n}) and "
                f"a right-hand side (m,), got {mat.shape} and {vec.shape}"
            )
        return mat, vec, eq

    def _no_lower(self, rows: int) -> FloatArray:
        """A read-only view of ``rows`` lower bounds at DAQP's -infinity (no allocation)."""
        if self._minus_inf.shape[0] < rows:
            self._minus_inf = np.full(2 * rows, -DAQP_INF)
            self._minus_inf.setflags(write=False)
        return self._minus_inf[:rows]

    @staticmethod
    def _as_arrays(mat: ArrayLike, vec: ArrayLike, name: str) -> tuple[NDArray, NDArray]:
        try:
            return np.asarray(mat, dtype=np.float64), np.asarray(vec, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"task {name!r}: rows must be real numbers") from None

    # ----- solve ----------------------------------------------------------------------------------
    def solve(self, levels: Sequence[Sequence[Task]]) -> HierarchyResult:
        """Solve the hierarchy ``levels`` (first = highest priority).

        Parameters
        ----------
        levels
            Each level a sequence of :class:`~.rows.Equality` / :class:`~.rows.Inequality` over
            ``n_vars`` variables. Empty levels and tasks with zero rows are allowed.

        Returns
        -------
        HierarchyResult
            Never NaN; an infeasible top level or a solver failure is a status, not an exception.

        Raises
        ------
        InputError
            If a task is not a row type or its arrays have the wrong shape.
        """
        t0 = time.perf_counter()
        if type(levels) is StackedLevels:
            A, bu, bl, counts = levels.A, levels.bu, levels.bl, levels.counts
        else:
            A, bu, bl, counts = self._stack(levels)
        m = A.shape[0]
        n_levels = len(counts)
        if m == 0:
            return self._result(
                np.zeros(self.n_vars), SolveStatus.OPTIMAL, n_levels, m, "", 1, 0, t0
            )

        # Upper bounds of +inf are "no bound"; NaN survives np.minimum. The sum is finite only
        # without NaN, -inf bounds and infinite equalities (whose lower bound is their value).
        np.minimum(bu, DAQP_INF, out=bu)
        # (Finite sums of squares prove the sum finite, in cheaper calls; see finite_total.)
        if not finite_total((A, bu, bl)):
            return self._result(
                np.zeros(self.n_vars), SolveStatus.INVALID_INPUT, n_levels, m, "", 0, 0, t0
            )

        nu = np.sqrt((A * A).dot(self._inv_metric))
        if min_reduce(nu) <= self.config.zero_row_tol:
            # Inactive stand-ins keep the row indices; their violation is reported below.
            zero = nu <= self.config.zero_row_tol
            A_d, bu_d, bl_d = A.copy(), bu.copy(), bl.copy()
            A_d[zero] = 0.0
            A_d[zero, 0] = 1.0
            bu_d[zero] = DAQP_INF
            bl_d[zero] = -DAQP_INF
        else:
            A_d, bu_d, bl_d = A, bu, bl

        layout = self._layout(counts)
        hard = self.config.hard_top_level and counts[0] > 0
        solver = "daqp" if hard else "daqp_soft"
        x, flag, iters = self._daqp(
            A_d, bu_d, bl_d, layout.hard_points if hard else layout.soft_points
        )
        if hard and flag not in _EXIT_SUCCESS:
            # Infeasible hard top level (-1, or 3 when a later level could not start from it),
            # dependent equalities (-6), or any other failure: retry with every level soft.
            solver = "daqp_soft"
            x, flag, iters = self._daqp(A_d, bu_d, bl_d, layout.soft_points)
        if flag not in _EXIT_SUCCESS or not finite_total((x,)):
            x, solver = self._fallback(levels)
            if x is None:
                return self._result(
                    np.zeros(self.n_vars), SolveStatus.FAILED, n_levels, m, "", flag, iters, t0
                )

        slack, satisfied, active = self._report(A, bu, bl, nu, layout, x)
        # A hard top level DAQP accepted is feasible; what the tolerance sees there is drift.
        top_ok = solver == "daqp" or bool(satisfied[0])
        if not top_ok:
            status = SolveStatus.TOP_LEVEL_INFEASIBLE
        elif and_reduce(satisfied[1:]):
            status = SolveStatus.OPTIMAL
        else:
            status = SolveStatus.RELAXED
        return HierarchyResult(
            x,
            status,
            slack,
            satisfied,
            active,
            solver,
            int(flag),
            int(iters),
            (time.perf_counter() - t0) * 1e6,
        )

    def evaluate(
        self, levels: Sequence[Sequence[Task]], x: ArrayLike
    ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Per-level violation norms and "holds" flags of ``levels`` at any point ``x``.

        The same report :meth:`solve` makes, for a point changed afterwards (a clamped torque).
        """
        if type(levels) is StackedLevels:
            A, bu, bl, counts = levels.A, levels.bu, levels.bl, levels.counts
        else:
            A, bu, bl, counts = self._stack(levels)
        x = np.asarray(x, dtype=np.float64).reshape(-1)
        if x.shape != (self.n_vars,):
            raise InputError(f"x: expected shape ({self.n_vars},), got {x.shape}")
        np.minimum(bu, DAQP_INF, out=bu)
        nu = np.sqrt((A * A).dot(self._inv_metric))
        slack, satisfied, _ = self._report(A, bu, bl, nu, self._layout(counts), x)
        return slack, satisfied

    def _layout(self, counts: list[int]) -> _Layout:
        """The :class:`_Layout` of ``counts`` (cached: a few layouts recur tick after tick)."""
        key = tuple(counts)
        layout = self._layouts.get(key)
        if layout is None:
            layout = _layout(counts)
            if len(self._layouts) < 64:
                self._layouts[key] = layout
        return layout

    def _report(
        self,
        A: FloatArray,
        bu: FloatArray,
        bl: FloatArray,
        nu: FloatArray,
        layout: _Layout,
        x: FloatArray,
    ) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.bool_]]:
        # For an equality bl == bu, so max(Ax - bu, bl - Ax) is |Ax - b|; for an inequality
        # bl = -1e30 leaves Ax - h. Rows within tolerance of their bound are active.
        n_levels = layout.hard_points.shape[0]
        slack = np.zeros(n_levels)
        satisfied = np.ones(n_levels, dtype=bool)
        if A.shape[0] == 0:
            return slack, satisfied, np.zeros(0, dtype=bool)
        Ax = A.dot(x)
        beyond = np.maximum(Ax - bu, bl - Ax)
        # -tol directly: (|b| + nu) * -ftol is exactly -((|b| + nu) * ftol), rounding being
        # symmetric in sign, and v + (-tol) is exactly v - tol.
        minus_tol = np.abs(bu)
        minus_tol += nu
        minus_tol *= -self.config.feasibility_tol
        active = beyond >= minus_tol
        viol = np.maximum(beyond, 0.0)
        nonempty, starts = layout.nonempty, layout.starts
        slack[nonempty] = np.sqrt(np.add.reduceat(viol * viol, starts))
        viol += minus_tol
        satisfied[nonempty] = np.maximum.reduceat(viol, starts) <= 0.0
        return slack, satisfied, active

    def _daqp(
        self, A: FloatArray, bu: FloatArray, bl: FloatArray, break_points: NDArray[np.intc]
    ) -> tuple[FloatArray, int, int]:
        """One DAQP call; ``break_points`` from a :class:`_Layout` (a leading 0 is an empty hard
        level: every real level is then soft). DAQP only reads them (it takes no read-only
        buffers, so the cached arrays stay writable; ``tests/core/test_contact_fast_paths.py``)."""
        m = A.shape[0]
        if self._sense.shape[0] < m:
            self._sense = np.zeros(2 * m, dtype=np.intc)
        # DAQP copies sense into its workspace, so one zero buffer serves every call.
        x, _, flag, info = daqp.solve(
            self._H, self._f, A, bu, bl, self._sense[:m], break_points, **self._settings
        )
        return x, int(flag), int(info["iterations"])

    def _fallback(self, levels: Sequence[Sequence[Task]]) -> tuple[FloatArray | None, str]:
        if self.config.fallback != "cascade":
            return None, ""
        try:
            res = solve_cascade(
                levels,
                self.n_vars,
                metric=self.metric,
                regularization=self.config.rho_soft,
                zero_row_tol=self.config.zero_row_tol,
                feasibility_tol=self.config.feasibility_tol,
            )
        except (ValueError, np.linalg.LinAlgError):
            return None, ""
        return (res.x, "cascade") if res.ok else (None, "")

    def _result(
        self,
        x: FloatArray,
        status: SolveStatus,
        n_levels: int,
        m: int,
        solver: str,
        flag: int,
        iters: int,
        t0: float,
    ) -> HierarchyResult:
        return HierarchyResult(
            x,
            status,
            np.zeros(n_levels),
            np.full(n_levels, status == SolveStatus.OPTIMAL),
            np.zeros(m, dtype=bool),
            solver,
            int(flag),
            int(iters),
            (time.perf_counter() - t0) * 1e6,
        )


def solve_hierarchy(
    levels: Sequence[Sequence[Task]],
    n_vars: int,
    config: HierarchyConfig | None = None,
    *,
    metric: ArrayLike | None = None,
) -> HierarchyResult:
    """One-shot :meth:`HierarchicalSolver.solve` (allocates a solver; keep one in a loop)."""
    return HierarchicalSolver(n_vars, config, metric=metric).solve(levels)
