"""Summaries of measured series for JSON reports: one place for the median / percentiles / max
that the run report, the hardware session report and the loop benchmark print."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["json_float", "summary"]


def json_float(x: float | None) -> float | None:
    """JSON-safe float: ``None`` for NaN, inf or missing."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def summary(
    values: ArrayLike,
    scale: float = 1.0,
    *,
    percentiles: Sequence[float] = (90, 99),
    count: bool = True,
    digits: int | None = None,
) -> dict[str, float | int | None]:
    """``{"n"?, "median", "p<q>"..., "max"}`` of the finite ``values * scale``.

    Non-finite values are left out; with none left every figure is ``None`` (``n`` is 0).
    ``digits`` rounds the figures.
    """
    v = np.asarray(values, dtype=np.float64) * scale
    v = v[np.isfinite(v)]
    keys = ["median", *(f"p{q:g}" for q in percentiles), "max"]
    out: dict[str, float | int | None] = {"n": int(v.size)} if count else {}
    if v.size == 0:
        return out | dict.fromkeys(keys)
    figures = [np.median(v), *(np.percentile(v, q) for q in percentiles), v.max()]
    for key, x in zip(keys, figures, strict=True):
        f = json_float(x)
        out[key] = round(f, digits) if f is not None and digits is not None else f
    return out
