"""Shared machinery of the least-squares fits: input preparation, scaled SVD and QR solves.

Every fit centres the points on their (weighted) centroid and divides by their RMS spread before
any decomposition, so a point set 1e3 m from the origin gives the same answer as the same set near
it, and every decomposition works on numbers of order one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import InputError
from ..validation import as_points

FloatArray = NDArray[np.float64]

_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)
_EZ = np.array([0.0, 0.0, 1.0])
_EZ.setflags(write=False)

#: Default relative rank tolerance: singular value ratios below it count as rank loss.
RANK_TOL = 1e-6
#: Default largest condition number of an equilibrated least-squares design.
MAX_COND = 1e7
# Smallest 1 - dF/dz used in a height's derivative: guards vertical tangents (silhouettes).
_MIN_SLOPE_DEN = 0.25


def _frozen(value: Any, fallback: FloatArray = _ZERO3) -> FloatArray:
    arr = np.array(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        arr = np.array(fallback, dtype=np.float64)
    arr.setflags(write=False)
    return arr


def _finite_float(value: float, fallback: float = 0.0) -> float:
    value = float(value)
    return value if np.isfinite(value) else fallback


# ----- input preparation -------------------------------------------------------------------------


@dataclass(frozen=True)
class _Prepared:
    """Finite rows with positive weight, centred on ``centroid`` and divided by ``scale``."""

    centroid: FloatArray
    scale: float
    local: FloatArray  # (N, 3) (p - centroid) / scale
    weights: FloatArray  # (N,) normalised to mean 1
    n: int


def _as_weights(weights: ArrayLike | None, n_rows: int) -> FloatArray | None:
    if weights is None:
        return None
    w = np.asarray(weights)
    if w.dtype == object or not (
        np.issubdtype(w.dtype, np.floating) or np.issubdtype(w.dtype, np.integer)
    ):
        raise InputError(f"weights: expected real numbers, got dtype {w.dtype}")
    if w.shape != (n_rows,):
        raise InputError(f"weights: expected shape ({n_rows},) to match points, got {w.shape}")
    w = w.astype(np.float64)
    if np.any(w < 0.0):
        raise InputError("weights: must be non-negative")
    return w


def _prepare(points: ArrayLike, weights: ArrayLike | None) -> _Prepared | str:
    """Validate, drop unusable rows, centre and scale; a string says why nothing is left."""
    p = as_points(points, "points")
    w = _as_weights(weights, p.shape[0])
    keep = np.isfinite(p).all(axis=1)
    if w is not None:
        keep &= np.isfinite(w) & (w > 0.0)
    if not keep.all():
        p = p[keep]
        w = None if w is None else w[keep]
    n = p.shape[0]
    if n == 0:
        return "no finite points"
    if w is not None:
        w = w / w.max()  # first by the largest: the mean of huge weights would overflow
    w = np.ones(n) if w is None else w / w.mean()
    # Subtract a sample first: the mean of the differences keeps full precision far from 0.
    ref = p[0]
    d = p - ref
    mean = (w @ d) / n
    local = d - mean
    scale = float(np.sqrt((w @ np.einsum("ij,ij->i", local, local)) / n))
    if not np.isfinite(scale):
        return "coordinates too large to fit"
    if not scale > 0.0:
        return "all points coincide"
    return _Prepared(ref + mean, scale, local / scale, w, n)


def _weighted_svd(prep: _Prepared) -> tuple[FloatArray, FloatArray]:
    """Singular values and right singular vectors of the weighted, centred, scaled points."""
    _, sv, vt = np.linalg.svd(prep.local * np.sqrt(prep.weights)[:, None], full_matrices=False)
    return sv, vt


def _solve(design: FloatArray, rhs: FloatArray, sqrt_w: FloatArray) -> tuple[FloatArray, float]:
    """Weighted least squares via SVD on an equilibrated design; returns (solution, cond)."""
    a = design * sqrt_w[:, None]
    norms = np.sqrt(np.einsum("ij,ij->j", a, a))
    if not np.all(norms > 0.0):
        return np.full(design.shape[1], np.nan), np.inf
    a /= norms
    sol, _, rank, sv = np.linalg.lstsq(a, rhs * sqrt_w, rcond=None)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0.0 else np.inf
    if rank < design.shape[1]:
        cond = np.inf
    return sol / norms, cond
