"""Every run states whether it was safe: one verdict from the truth margin, one line, one code.

A run is ``SAFE`` when the HIP sphere never went more than ``allowed_penetration_m`` (default
2 mm) into any true surface, ``UNSAFE`` otherwise; the line names the worst moment and what the
tick knew then (``UNSAFE: min margin -24.7 mm at t=3.41 s (reason: no valid estimate for 812
ms)``). Without a truth (real hardware) there is no verdict on the patient, only what the
estimate saw: ``NO TRUTH: ...`` with the smallest estimated distance and the holds and stops.

The command line exits with :data:`UNSAFE_EXIT_CODE` on an UNSAFE run.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..haptics.unknown import SpaceState

FloatArray = NDArray[np.float64]

#: Exit code of a run that ends UNSAFE (2 is bad input, 1 a failure to run).
UNSAFE_EXIT_CODE = 3

#: Penetration (m) a run may show and still be SAFE.
ALLOWED_PENETRATION_M = 0.002


@dataclass(frozen=True)
class Verdict:
    """The verdict of one run (``safe`` is ``None`` without a truth)."""

    safe: bool | None
    min_margin_m: float | None
    t_min_s: float | None
    reason: str
    allowed_penetration_m: float = ALLOWED_PENETRATION_M

    @property
    def label(self) -> str:
        return "NO TRUTH" if self.safe is None else ("SAFE" if self.safe else "UNSAFE")

    @property
    def exit_code(self) -> int:
        return UNSAFE_EXIT_CODE if self.safe is False else 0

    def line(self) -> str:
        """The run's last line, e.g. ``UNSAFE: min margin -24.7 mm at t=3.41 s (reason: ...)``."""
        if self.min_margin_m is None or self.t_min_s is None:
            return f"{self.label}: {self.reason}"
        where = f"min margin {self.min_margin_m * 1e3:+.1f} mm at t={self.t_min_s:.2f} s"
        if self.safe is None:
            return f"{self.label}: estimated {where} ({self.reason})"
        allowed = f"allowed -{self.allowed_penetration_m * 1e3:.1f} mm"
        if self.safe:
            return f"SAFE: {where} ({allowed})"
        return f"UNSAFE: {where} ({allowed}; reason: {self.reason})"

    def to_json(self) -> dict[str, Any]:
        return {
            "verdict": self.label,
            "safe": self.safe,
            "line": self.line(),
            "min_margin_m": _finite_or_none(self.min_margin_m),
            "t_min_margin_s": _finite_or_none(self.t_min_s),
            "reason": self.reason,
            "allowed_penetration_m": self.allowed_penetration_m,
        }


def judge(
    t: FloatArray,
    margin: FloatArray,
    *,
    space: FloatArray | None = None,
    fused_age_s: FloatArray | None = None,
    allowed_penetration_m: float = ALLOWED_PENETRATION_M,
) -> Verdict:
    """The verdict from per-tick times ``t`` (s) and true margins ``margin`` (m).

    ``space`` (the tick's :class:`SpaceState` codes) and ``fused_age_s`` (age of the newest valid
    estimate, negative or inf when none) explain an UNSAFE moment.
    """
    finite = np.isfinite(margin)
    if margin.size == 0 or not finite.any():
        return Verdict(
            None, None, None, "no true surface to measure against", allowed_penetration_m
        )
    i = int(np.argmin(np.where(finite, margin, np.inf)))
    worst = float(margin[i])
    safe = worst >= -allowed_penetration_m
    reason = "" if safe else _why(i, t, space, fused_age_s)
    return Verdict(safe, worst, float(t[i]), reason, allowed_penetration_m)


def _why(i: int, t: FloatArray, space: FloatArray | None, age: FloatArray | None) -> str:
    """What the tick knew at tick ``i`` (the worst moment)."""
    if space is not None and int(space[i]) != SpaceState.KNOWN:
        state = SpaceState(int(space[i]))
        j = i
        while j > 0 and int(space[j - 1]) != SpaceState.KNOWN:
            j -= 1
        return f"space {state.label} for {(t[i] - t[j]) * 1e3:.0f} ms"
    if age is not None:
        a = float(age[i])
        if not (math.isfinite(a) and a >= 0.0):
            return "no valid estimate yet"
        if a > 0.1:
            return f"no valid estimate for {a * 1e3:.0f} ms"
    return "the constraints did not hold (estimate error or too little torque)"


def judge_estimates(
    t: FloatArray,
    d_proj_estimated_m: FloatArray,
    d_proj_true_m: FloatArray,
    allowed_m: float = ALLOWED_PENETRATION_M,
) -> Verdict:
    """Open-loop runs (no control): SAFE when no valid estimate put the surface more than
    ``allowed_m`` farther from the HIP than it truly was (the optimistic, unsafe side).

    The margin judged is ``d_true - d_estimated`` (negative = optimistic) per estimate.
    """
    margin = np.asarray(d_proj_true_m, dtype=np.float64) - np.asarray(d_proj_estimated_m)
    v = judge(np.asarray(t, dtype=np.float64), margin, allowed_penetration_m=allowed_m)
    if v.safe is False:
        return Verdict(
            False, v.min_margin_m, v.t_min_s, "an estimate reported the surface farther", allowed_m
        )
    if v.safe is None:
        return Verdict(None, None, None, "no valid estimate to judge", allowed_m)
    return v


def no_truth(
    min_estimated_margin_m: float | None, t_min_s: float | None, events: Sequence[str]
) -> Verdict:
    """A run without a truth: the smallest distance the estimate saw, and its holds/stops."""
    said = "; ".join(events) if events else "no hold, no stop"
    return Verdict(None, min_estimated_margin_m, t_min_s, said)


def space_summary(
    t: FloatArray, space: FloatArray, transitions: Sequence[Any], dt: float
) -> dict[str, Any]:
    """Share of the run per :class:`SpaceState` and the transitions (time, state, reason)."""
    n = max(1, space.size)
    counts = {s.label: float(np.count_nonzero(space == s)) / n for s in SpaceState}
    longest = 0.0
    run = 0
    for code in space.tolist():
        run = run + 1 if code != SpaceState.KNOWN else 0
        longest = max(longest, run * dt)
    return {
        "fraction": counts,
        "longest_unknown_s": longest,
        "transitions": [[float(tr.t), tr.state.label, tr.reason] for tr in transitions],
    }


def _finite_or_none(x: float | None) -> float | None:
    return x if x is not None and math.isfinite(x) else None


__all__ = [
    "ALLOWED_PENETRATION_M",
    "UNSAFE_EXIT_CODE",
    "Verdict",
    "judge",
    "judge_estimates",
    "no_truth",
    "space_summary",
]
