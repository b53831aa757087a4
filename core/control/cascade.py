"""An independent level-by-level cascade of quadratic programs (quadprog): the cross-check.

The production solver (:mod:`.hierarchy`) hands the whole hierarchy to DAQP's hierarchical mode in
one call. This module solves the same problem the slow, transparent way, one quadprog QP per level,
so the two can be compared on random and structured problems; the hierarchy also falls back on it
when DAQP reports a failure.

The problem, for levels ``k = 1..p`` of rows ``a_i x = b_i`` or ``a_i x <= b_i``:

- level ``k`` minimises ``sum_i (r_i / nu_i)^2 + rho * |x|_H^2`` over the optimal set of the levels
  above, where ``r_i`` is row ``i``'s violation (``a_i x - b_i`` for an equality, its positive part
  for an inequality) and ``nu_i = |a_i|_{H^-1}`` the row's length in the metric ``H = diag(metric)``
  (DAQP normalises its rows this way, so scaling a row does not change a compromise);
- the optimal set of a level keeps its equalities at their optimal residual (``a_i x = a_i x_k``)
  and its inequalities relaxed by their optimal slack (``a_i x <= max(b_i, a_i x_k)``);
- after the last level, ``x`` is the ``H``-minimum-norm point of the optimal set.

Equalities fixed by a level are eliminated with a null-space basis (SVD, so duplicate and
dependent rows are harmless); inequalities stay inequalities of the later QPs. Each level's QP
(in the null-space coordinates and the level's slacks) is slightly regularised for quadprog, then
polished: with its active set known the level is an equality-constrained least-squares problem,
solved exactly. The cascade costs milliseconds; it is a reference, not a real-time solver.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import quadprog
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from .rows import Equality, Inequality, task_parts

FloatArray = NDArray[np.float64]

# Relative loosening of the relaxed rows of the levels above (see _room).
_RELAX_MARGIN = 1e-10
# Singular values of (normalised) fixed equality rows below this count as zero (rank decision).
_RANK_TOL = 1e-9


class CascadeResult(NamedTuple):
    """What :func:`solve_cascade` returns.

    Attributes
    ----------
    x
        The solution (decision variables), never NaN.
    level_slack
        Euclidean norm of each level's violations, rows in their own units, shape ``(p,)``.
    level_satisfied
        Whether every row of the level holds within the tolerance.
    ok
        False when a QP failed (``x`` is then the best point reached before the failure).
    """

    x: FloatArray
    level_slack: FloatArray
    level_satisfied: NDArray[np.bool_]
    ok: bool


class _LevelRows(NamedTuple):
    A: FloatArray  # equality rows, normalised by nu
    b: FloatArray
    G: FloatArray  # inequality rows, normalised by nu
    h: FloatArray
    # raw rows for the violation report
    raw: FloatArray
    rhs: FloatArray
    is_eq: NDArray[np.bool_]


def _stack_level(
    level: Sequence[Equality | Inequality],
    n_vars: int,
    inv_sqrt_metric: FloatArray,
    zero_row_tol: float,
) -> _LevelRows:
    mats, rhs, kinds = [], [], []
    for task in level:
        mat, vec, eq = task_parts(task, "level task")
        mat = np.asarray(mat, dtype=np.float64)
        vec = np.asarray(vec, dtype=np.float64)
        if mat.ndim != 2 or mat.shape[1] != n_vars or vec.shape != (mat.shape[0],):
            raise InputError(
                f"task {task[2]!r}: expected rows ({mat.shape[0] if mat.ndim else '?'}, {n_vars}) "
                f"and a matching right-hand side, got {mat.shape} and {vec.shape}"
            )
        mats.append(mat)
        rhs.append(vec)
        kinds.append(np.full(mat.shape[0], eq))
    if not mats:
        empty = np.zeros((0, n_vars))
        return _LevelRows(
            empty, np.zeros(0), empty, np.zeros(0), empty, np.zeros(0), np.zeros(0, dtype=bool)
        )
    raw = np.vstack(mats)
    b = np.concatenate(rhs)
    is_eq = np.concatenate(kinds)
    nu = np.linalg.norm(raw * inv_sqrt_metric, axis=1)
    # A row of (near) zero length cannot be moved by x; it is reported, never normalised.
    live = nu > zero_row_tol
    # An inequality with an infinite bound is no constraint at all.
    live &= is_eq | (b < np.inf)
    scale = np.where(live, nu, 1.0)
    An = raw / scale[:, None]
    bn = b / scale
    eq_rows = live & is_eq
    in_rows = live & ~is_eq
    return _LevelRows(An[eq_rows], bn[eq_rows], An[in_rows], bn[in_rows], raw, b, is_eq)


def _violation(rows: _LevelRows, x: FloatArray) -> FloatArray:
    if rows.raw.shape[0] == 0:
        return np.zeros(0)
    with np.errstate(invalid="ignore"):
        r = rows.raw @ x - rows.rhs
    return np.where(rows.is_eq, np.abs(r), np.maximum(np.nan_to_num(r, nan=0.0, neginf=0.0), 0.0))


def _qp(P: FloatArray, q: FloatArray, C: FloatArray, d: FloatArray) -> tuple[FloatArray, NDArray]:
    """``min 1/2 z'Pz + q'z  s.t.  C z <= d`` with quadprog; returns ``z`` and the active rows."""
    if C.shape[0] == 0:
        return np.linalg.solve(P, -q), np.zeros(0, dtype=int)
    out = quadprog.solve_qp(P, -q, -C.T, -d, 0)
    iact = np.asarray(out[5], dtype=int)
    return out[0], iact[iact > 0] - 1


def _polish(
    y: FloatArray,
    active: NDArray,
    AZ: FloatArray,
    c: FloatArray,
    GZ: FloatArray,
    e: FloatArray,
    CZ: FloatArray,
    dh: FloatArray,
) -> FloatArray:
    """Remove the regularisation's bias from a level's ``y`` once its active set is known.

    With the rows that need slack (``GZ y - e`` active) and the hard rows at their bound known,
    the level is an equality-constrained least-squares problem; it is solved exactly (SVD) for
    the smallest step from ``y``. The step is kept only if it changes no activity and does not
    increase the objective.
    """
    mi = GZ.shape[0]
    lvl = active[active < mi]
    hard = active[active >= mi] - mi
    A_eff = np.vstack([AZ, GZ[lvl]])
    c_eff = np.concatenate([c, e[lvl]])
    C_act = CZ[hard]
    step = np.linalg.lstsq(C_act, dh[hard] - C_act @ y, rcond=None)[0] if hard.size else 0.0 * y
    N = _null_space(C_act)
    if N.shape[1] and A_eff.shape[0]:
        base = y + step
        w = np.linalg.lstsq(A_eff @ N, c_eff - A_eff @ base, rcond=1e-12)[0]
        step = step + N @ w
    y_new = y + step

    def objective(v: FloatArray) -> float:
        r = AZ @ v - c
        s = np.maximum(GZ @ v - e, 0.0)
        return float(r @ r + s @ s)

    tol_h = 1e-9 * (1.0 + np.abs(dh))
    tol_e = 1e-9 * (1.0 + np.abs(e))
    inactive = np.setdiff1d(np.arange(mi), lvl)
    ok = bool(np.all(CZ @ y_new <= dh + tol_h))
    ok &= bool(np.all(GZ[inactive] @ y_new <= (e + tol_e)[inactive]))
    ok &= objective(y_new) <= objective(y) * (1.0 + 1e-12) + 1e-18
    return y_new if ok else y


def _room(bound: FloatArray, value: FloatArray) -> FloatArray:
    """``bound - value`` for the relaxed rows of the levels above, made strictly positive.

    The point reached so far satisfies them up to quadprog's rounding, so never ask for more
    (max with 0); then loosen each by a tiny margin that differs from row to row, so ``y = 0``
    is strictly feasible and duplicate, pinched (``x <= 1, x >= 1``) or otherwise degenerate rows
    never become active together, which Goldfarb-Idnani reports as "inconsistent constraints".
    """
    spread = 1.0 + (np.arange(bound.size) % 7) / 7.0
    return np.maximum(bound - value, 0.0) + _RELAX_MARGIN * spread * (1.0 + np.abs(bound))


def _null_space(N: FloatArray) -> FloatArray:
    if N.shape[0] == 0:
        return np.eye(N.shape[1])
    _, s, vt = np.linalg.svd(N)
    rank = int(np.sum(s > _RANK_TOL))
    return vt[rank:].T


def solve_cascade(
    levels: Sequence[Sequence[Equality | Inequality]],
    n_vars: int,
    *,
    metric: ArrayLike | None = None,
    regularization: float = 1e-8,
    zero_row_tol: float = 1e-10,
    feasibility_tol: float = 1e-7,
) -> CascadeResult:
    """Solve a task hierarchy level by level with quadprog.

    Parameters
    ----------
    levels
        Levels in priority order (first = highest), each a sequence of tasks.
    n_vars
        Number of decision variables.
    metric
        Diagonal of ``H`` (positive), the metric of the Tikhonov term and of the row lengths
        ``nu_i``; ones by default.
    regularization
        Weight of ``|x|_H^2`` against the normalised slacks inside each level's QP, only so that
        quadprog sees a strictly convex problem; once the QP has found the level's active set,
        the level is re-solved exactly (SVD) without it, so the result is the lexicographic
        optimum, not a regularised one.
    zero_row_tol
        Rows shorter than this (in the metric) are treated as rows of zeros.
    feasibility_tol
        A row holds when its violation is below ``tol * (nu_i + |b_i|)``.

    Returns
    -------
    CascadeResult
    """
    if n_vars < 1:
        raise InputError(f"n_vars = {n_vars}: must be at least 1")
    w = np.ones(n_vars) if metric is None else np.asarray(metric, dtype=np.float64).reshape(-1)
    if w.shape != (n_vars,) or not np.all(np.isfinite(w)) or not np.all(w > 0):
        raise InputError(f"metric: expected {n_vars} positive finite numbers")
    inv_sqrt = 1.0 / np.sqrt(w)
    H = np.diag(w)

    stacked = [_stack_level(level, n_vars, inv_sqrt, zero_row_tol) for level in levels]
    x = np.zeros(n_vars)
    Z = np.eye(n_vars)
    hard_G = np.zeros((0, n_vars))
    hard_h = np.zeros(0)
    ok = True
    for rows in stacked:
        if Z.shape[1] == 0:
            break
        r = Z.shape[1]
        AZ = rows.A @ Z
        GZ = rows.G @ Z
        mi = GZ.shape[0]
        P = np.zeros((r + mi, r + mi))
        P[:r, :r] = AZ.T @ AZ + regularization * (Z.T @ H @ Z)
        P[r:, r:] = np.eye(mi)
        q = np.zeros(r + mi)
        q[:r] = AZ.T @ (rows.A @ x - rows.b) + regularization * (Z.T @ (H @ x))
        C = np.zeros((mi + hard_G.shape[0], r + mi))
        C[:mi, :r] = GZ
        C[:mi, r:] = -np.eye(mi)
        C[mi:, :r] = hard_G @ Z
        d = np.concatenate([rows.h - rows.G @ x, _room(hard_h, hard_G @ x)])
        try:
            z, active = _qp(P, q, C, d)
            y = _polish(z[:r], active, AZ, rows.b - rows.A @ x, GZ, d[:mi], C[mi:, :r], d[mi:])
        except (ValueError, np.linalg.LinAlgError):
            ok = False
            break
        x = x + Z @ y
        # The level's optimal set: equalities kept at their residual, inequalities relaxed.
        Z = Z @ _null_space(AZ)
        relaxed = np.maximum(rows.h, rows.G @ x)
        hard_G = np.vstack([hard_G, rows.G])
        hard_h = np.concatenate([hard_h, relaxed])

    if ok and Z.shape[1] > 0:
        # Tie-break: the H-minimum-norm point of what the levels left free.
        C = hard_G @ Z
        d = _room(hard_h, hard_G @ x)
        try:
            y = _qp(Z.T @ H @ Z, Z.T @ (H @ x), C, d)[0]
            x = x + Z @ y
        except (ValueError, np.linalg.LinAlgError):
            ok = False

    if not np.all(np.isfinite(x)):
        x = np.zeros(n_vars)
        ok = False
    slack = np.zeros(len(stacked))
    satisfied = np.ones(len(stacked), dtype=bool)
    for k, rows in enumerate(stacked):
        v = _violation(rows, x)
        slack[k] = float(np.sqrt(np.sum(v * v)))
        nu = np.linalg.norm(rows.raw * inv_sqrt, axis=1)
        tol = feasibility_tol * (nu + np.minimum(np.abs(rows.rhs), 1e30))
        satisfied[k] = bool(np.all(v <= tol))
    return CascadeResult(x, slack, satisfied, ok)
