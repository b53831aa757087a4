"""``hapticloud bench safety``: the shipped scenes under the degradations a clinic meets.

Each row is one degradation (a set of ``--set`` overrides on every camera of the scene, or on
the first camera only), each column a scene; a cell is one deterministic closed-loop run judged
against the simulator's truth (:mod:`.verdict`): the smallest true margin, the share of the run
the tick spent without knowing the space (holding the last surface or stopped) and the verdict.
The target is every cell SAFE (never more than 2 mm into a body), with the robot held only where
it could not see.

The table runs its cells in worker processes, and the hardware path (real time, a second
process holding one core) is not deterministic: both live in
:mod:`hapticloud.hardware.session.safety_bench`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from ..scene import load_scene

#: The shipped scenes that have cameras (the others have nothing to degrade).
SCENES = ("demo", "impacts", "sliding")


@dataclass(frozen=True)
class Degradation:
    """One row: a name and the overrides it applies to each camera (``both``) or the first."""

    name: str
    camera: Mapping[str, Any]
    both: bool = True
    extra: Mapping[str, Any] | None = None


def degradations() -> list[Degradation]:
    """The rows of the table (the issue's list, in its order)."""
    rows = [Degradation("healthy (as shipped)", {})]
    for d in (2, 4, 8, 16):
        rows.append(Degradation(f"decimation {d}, one camera", {"decimation": d}, both=False))
        rows.append(Degradation(f"decimation {d}, both cameras", {"decimation": d}))
    rows.append(Degradation("one camera stops at 1 s", {"stop_s": 1.0}, both=False))
    rows.append(Degradation("both cameras stop at 1 s", {"stop_s": 1.0}))
    for ms in (50, 150, 400):
        rows.append(Degradation(f"frames delayed {ms} ms", {"latency_s": ms / 1000.0}))
    for pct in (10, 50):
        rows.append(Degradation(f"frames dropped {pct} %", {"drop_fraction": pct / 100.0}))
    rows.append(
        Degradation(
            "perception slowed (7 Hz, 146 ms a frame)", {"rate_hz": 7.0, "latency_s": 0.146}
        )
    )
    rows.append(
        Degradation(
            "largest legal voxel (= max_spacing_m)",
            {},
            extra={"perception.voxel.voxel_size_m": "max_spacing"},
        )
    )
    return rows


def overrides_for(scene_name: str, row: Degradation) -> dict[str, Any]:
    """The ``--set`` overrides of ``row`` for the scene's cameras."""
    scene = load_scene(scene_name)
    names = [c.name for c in scene.cameras]
    out: dict[str, Any] = {}
    for name in names if row.both else names[:1]:
        for key, value in row.camera.items():
            out[f"cameras.{name}.{key}"] = value
    for key, value in (row.extra or {}).items():
        if value == "max_spacing":
            value = scene.config.perception.max_spacing_m
        out[key] = value
    return out


def run_cell(scene_name: str, row: Degradation, duration_s: float | None) -> dict[str, Any]:
    """One deterministic run of ``scene_name`` under ``row``: margin, time unknown, verdict."""
    from .run import report, run_scene

    sets = overrides_for(scene_name, row)
    return cell_from_report(
        scene_name, row.name, sets, report(run_scene(scene_name, sets, duration_s))
    )


def cell_from_report(
    scene: str, degradation: str, sets: Mapping[str, Any], rep: Mapping[str, Any]
) -> dict[str, Any]:
    """A table cell from a run's report (``hapticloud run`` or ``run --hardware``: both carry
    ``truth``, ``space`` and ``verdict``)."""
    truth = rep["truth"]
    space = rep["space"] or {"fraction": {"holding": 0.0, "stopped": 0.0}, "longest_unknown_s": 0}
    margin = truth.get("min_margin_m")
    return {
        "scene": scene,
        "degradation": degradation,
        "set": dict(sets),
        "min_margin_mm": None if margin is None else round(margin * 1e3, 2),
        "t_min_margin_s": truth.get("t_min_margin_s"),
        "held_fraction": round(space["fraction"]["holding"], 4),
        "stopped_fraction": round(space["fraction"]["stopped"], 4),
        "longest_unknown_s": round(space["longest_unknown_s"], 3),
        "verdict": rep["verdict"],
        "line": truth["line"],
    }


def table_lines(cells: Sequence[Mapping[str, Any]], scenes: Sequence[str]) -> list[str]:
    """A Markdown table: degradation x scene -> min margin, time held/stopped, verdict."""
    by = {(c["degradation"], c["scene"]): c for c in cells}
    names = list(dict.fromkeys(c["degradation"] for c in cells))
    head = "| degradation | " + " | ".join(scenes) + " |"
    lines = [head, "|---" * (len(scenes) + 1) + "|"]
    for name in names:
        row = [name]
        for scene in scenes:
            c = by.get((name, scene))
            row.append("" if c is None else cell_text(c))
        lines.append("| " + " | ".join(row) + " |")
    return lines


def cell_text(c: Mapping[str, Any]) -> str:
    """``+1.3 mm, held 4 %, stopped 0 %, SAFE``."""
    m = c["min_margin_mm"]
    margin = "n/a" if m is None or not math.isfinite(m) else f"{m:+.1f} mm"
    return (
        f"{margin}, held {c['held_fraction']:.0%}, stopped {c['stopped_fraction']:.0%}, "
        f"{c['verdict']}"
    )


def all_safe(cells: Sequence[Mapping[str, Any]]) -> bool:
    return all(c["verdict"] != "UNSAFE" for c in cells)


__all__ = [
    "SCENES",
    "Degradation",
    "all_safe",
    "cell_from_report",
    "cell_text",
    "degradations",
    "overrides_for",
    "run_cell",
    "table_lines",
]
