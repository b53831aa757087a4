"""The non-dominated trials of a study, the presets picked from them, and the printed table.

The front is over :data:`FRONT_OBJECTIVES`, all minimised: the median latency from the depth
frame and three errors against the truth: the centroid's median and p90 (the tail the voxel and
the quadric's bandwidth move; the median barely does) and the p90 of ``|d_proj|`` (the distance
the haptic constraints act on), plus the fused surface's tracking error when the study turns
closed-loop knobs. A trial is on the front when no other is at least as good in all of them and
better in one. Unsafe trials and trials with a figure missing are never on it.

Presets (:func:`pick_presets`), each a point of the front:

- ``fast``: the lowest latency whose p90 centroid error still meets the perception target
  (:data:`ACCURACY_TARGET_MM`);
- ``accurate``: the lowest p90 centroid error whose median latency is at most
  :data:`ACCURATE_LATENCY_FACTOR` times the shipped default's, measured in the same study;
- ``balanced``: the knee: the point nearest the ideal (best latency, best error) with both
  figures scaled to the front's range.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import tomli_w

from .evaluate import TrialResult

FRONT_OBJECTIVES = (
    "latency_ms_median",
    "centroid_mm_median",
    "centroid_mm_p90",
    "d_proj_mm_p90",
)
#: The two figures the presets and the plot trade: latency and the p90 centroid error.
TRADE = ("latency_ms_median", "centroid_mm_p90")
LOOP_FRONT_OBJECTIVE = "tracking_error_mm"
ACCURACY_TARGET_MM = 5.0  #: the perception target for the p90 centroid error
ACCURATE_LATENCY_FACTOR = 1.25
PRESETS = ("fast", "balanced", "accurate")


def front_objectives(trials: Sequence[TrialResult]) -> tuple[str, ...]:
    loop = any(math.isfinite(t.objectives.get(LOOP_FRONT_OBJECTIVE, math.nan)) for t in trials)
    return (*FRONT_OBJECTIVES, LOOP_FRONT_OBJECTIVE) if loop else FRONT_OBJECTIVES


def _vector(trial: TrialResult, names: Sequence[str]) -> tuple[float, ...] | None:
    values = tuple(float(trial.objectives.get(n, math.nan)) for n in names)
    return values if all(math.isfinite(v) for v in values) else None


def dominates(a: Sequence[float], b: Sequence[float]) -> bool:
    """``a`` is no worse than ``b`` everywhere and better somewhere (all minimised)."""
    return all(x <= y for x, y in zip(a, b, strict=True)) and any(
        x < y for x, y in zip(a, b, strict=True)
    )


def pareto_front(trials: Sequence[TrialResult], names: Sequence[str] | None = None) -> list[int]:
    """Indices of the safe trials no other safe trial dominates (over ``names``)."""
    names = front_objectives(trials) if names is None else tuple(names)
    vectors = {
        i: v for i, t in enumerate(trials) if not t.unsafe and (v := _vector(t, names)) is not None
    }
    return [
        i
        for i, v in vectors.items()
        if not any(dominates(w, v) for j, w in vectors.items() if j != i)
    ]


def pick_presets(
    trials: Sequence[TrialResult], front: Sequence[int], default_index: int | None
) -> dict[str, int]:
    """Preset name -> trial index, picked from ``front`` (see the module docstring)."""
    if not front:
        return {}
    lat, err = TRADE
    by_latency = sorted(front, key=lambda i: trials[i].objectives[lat])
    meets = [i for i in by_latency if trials[i].objectives[err] <= ACCURACY_TARGET_MM]
    fast = meets[0] if meets else min(front, key=lambda i: trials[i].objectives[err])
    budget = math.inf
    if default_index is not None and math.isfinite(trials[default_index].objectives[lat]):
        budget = ACCURATE_LATENCY_FACTOR * trials[default_index].objectives[lat]
    affordable = [i for i in front if trials[i].objectives[lat] <= budget] or list(front)
    accurate = min(affordable, key=lambda i: (trials[i].objectives[err], trials[i].objectives[lat]))
    lats = [trials[i].objectives[lat] for i in front]
    errs = [trials[i].objectives[err] for i in front]
    span_l = (max(lats) - min(lats)) or 1.0
    span_e = (max(errs) - min(errs)) or 1.0

    def knee(i: int) -> float:
        o = trials[i].objectives
        return math.hypot((o[lat] - min(lats)) / span_l, (o[err] - min(errs)) / span_e)

    balanced = min(front, key=knee)
    return {"fast": fast, "balanced": balanced, "accurate": accurate}


def preset_toml(params: Mapping[str, Any], header: Sequence[str]) -> str:
    """A preset file: the knobs as TOML tables (every other parameter keeps its default), with
    ``header`` as comments (how it was made)."""
    nested: dict[str, Any] = {}
    for key, value in sorted(params.items()):
        *tables, leaf = key.split(".")
        node = nested
        for table in tables:
            node = node.setdefault(table, {})
        node[leaf] = value
    comments = "".join(f"# {line}\n" for line in header)
    return comments + tomli_w.dumps(nested)


def _cell(value: Any, width: int, digits: int = 2) -> str:
    if isinstance(value, float):
        text = "-" if not math.isfinite(value) else f"{value:.{digits}f}"
    else:
        text = str(value)
    return f"{text:>{width}s}"


def format_table(
    trials: Sequence[TrialResult],
    front: Sequence[int],
    keys: Sequence[str],
    presets: Mapping[str, int] | None = None,
) -> str:
    """One row per trial, the non-dominated marked ``*`` and unsafe ``!``, sorted by latency."""
    presets = presets or {}
    names: dict[int, str] = {}
    for name, i in presets.items():
        names[i] = f"{names[i]}+{name}" if i in names else name
    loop = LOOP_FRONT_OBJECTIVE in front_objectives(trials)
    short = [k.split(".")[-1][:14] for k in keys]
    head = "  ".join(f"{s:>14s}" for s in short)
    cols = "  lat med  lat p90  c med  c p90  dproj90  n deg  valid"
    cols += "  margin  track" if loop else ""
    lines = [f"   {head}  {cols}  worker"]
    order = sorted(
        range(len(trials)),
        key=lambda i: (trials[i].unsafe, trials[i].objectives.get("latency_ms_median", math.inf)),
    )
    for i in order:
        t = trials[i]
        o = t.objectives
        mark = "!" if t.unsafe else ("*" if i in front else " ")
        values = "  ".join(_cell(t.params.get(k, "-"), 14, 4) for k in keys)
        row = (
            f"{mark}  {values}  {_cell(o['latency_ms_median'], 7)}  {_cell(o['latency_ms_p90'], 7)}"
            f"  {_cell(o['centroid_mm_median'], 5)}  {_cell(o['centroid_mm_p90'], 5)}"
            f"  {_cell(o['d_proj_mm_p90'], 7)}  {_cell(o['normal_deg_median'], 5)}"
            f"  {_cell(100 * o['valid_share'], 4, 0)}%"
        )
        if loop:
            row += f"  {_cell(o['min_margin_mm'], 6, 1)}  {_cell(o['tracking_error_mm'], 5)}"
        row += f"  {t.worker}"
        if i in names:
            row += f"  <- {names[i]}"
        if t.unsafe:
            row += f"  UNSAFE: {'; '.join(t.reasons)}"
        lines.append(row)
    return "\n".join(lines)


__all__ = [
    "ACCURACY_TARGET_MM",
    "ACCURATE_LATENCY_FACTOR",
    "FRONT_OBJECTIVES",
    "PRESETS",
    "TRADE",
    "dominates",
    "format_table",
    "front_objectives",
    "pareto_front",
    "pick_presets",
    "preset_toml",
]
