"""``hapticloud run``: a headless closed-loop session of a scene, and its report against the truth.

:func:`run_scene` assembles the scene (:func:`~hapticloud.core.scene.assembly.assemble`) and runs
it in the closed loop (:class:`~hapticloud.core.sim.closed_loop.ClosedLoopSim`); :func:`report`
turns the record into the JSON report; :func:`sweep` repeats a scene over the values of one
parameter (and, with ``compare_paper``, with the paper's formulation too: no surface-velocity
feed-forward in either constraint), which is what Fig. 12 plots.

Report keys (all SI; ``None`` where a quantity does not exist, e.g. no cameras):

- ``min_margin_m``: the smallest true free distance between the HIP sphere (radius
  ``hip_radius_m``) and every true surface (patient bodies, walls) over the run; negative is
  penetration. ``max_penetration_m = max(0, -min_margin_m)``. ``min_center_margin_m`` is the
  same for the HIP centre (``min_margin_m + hip_radius_m``), the quantity the paper's 1.0 m/s
  statement is about.
- ``estimates``: per camera, the raw 30 Hz estimates against the truth at their HIP (frames with
  the surface within ``NEAR_M`` of the HIP sphere): centroid error (mm), normal error (deg),
  ``d_proj`` error (mm, positive = the surface reported farther than it is: the unsafe side);
  and the fused 800 Hz surface against the truth at every tick (same errors), plus the largest
  change of the fused normal between two ticks (deg) and its 99th percentile.
- ``control``: tick, controller step and solve times (µs: median, p99, max), deadline misses
  (ticks over the 1250 µs period) per 10,000 ticks, controller statuses, clamped ticks.
- ``constraints``: fraction of ticks with rows / binding per constraint, with a violated level 4.
- ``contacts``: each contact episode (true margin under ``CONTACT_M``): approach speed before it,
  speed at contact, the deepest point within ``IMPACT_WINDOW_S`` of contact (penetration), and
  the rebound: the margin regained and the outward speed within ``REBOUND_WINDOW_S`` after it.
  ``min_margin_m`` of an episode is over the whole episode.
- ``contact_jitter_mm``: standard deviation of the true margin around its 0.1 s moving average
  while in contact (oscillation).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..control import ControlStatus
from ..errors import ConfigError
from ..loop import FORCE, POSITIONAL, VELOCITY
from ..scene import Scene, load_scene
from ..scene.assembly import assemble
from ..sim.closed_loop import STATUS_CODES, ClosedLoopSim, RunRecord
from .stats import json_float, summary
from .verdict import Verdict, judge, space_summary

FloatArray = NDArray[np.float64]

NEAR_M = 0.15  #: estimates count where the true free distance is below this (m)
CONTACT_M = 0.005  #: a contact episode: true margin below this (m)
IMPACT_WINDOW_S = 0.15  #: the impact's deepest point is sought this long after contact (s)
REBOUND_WINDOW_S = 0.15  #: rebound is measured this long after the deepest point (s)
DEADLINE_US = 1250.0  #: one 800 Hz period

PAPER_OVERRIDES: dict[str, Any] = {
    "haptics.positional.surface_velocity_feedforward": False,
    "haptics.velocity.surface_velocity_feedforward": False,
}


# ----- running -----------------------------------------------------------------------------------
def run_scene(
    scene: Scene | str | Path,
    overrides: Mapping[str, Any] | None = None,
    duration_s: float | None = None,
    progress: Callable[[float], None] | None = None,
    frame_sink: Callable[..., None] | None = None,
) -> RunRecord:
    """Load (if a path), build and run a scene; see :class:`ClosedLoopSim` (``frame_sink``: its
    hook for each processed camera frame, e.g. a recorder's)."""
    if not isinstance(scene, Scene):
        scene = load_scene(scene, overrides)
    elif overrides:
        scene = scene.with_overrides(overrides)
    if duration_s is not None and not (math.isfinite(duration_s) and duration_s > 0.0):
        raise ConfigError(f"--duration = {duration_s}: must be a positive number of seconds")
    sim = ClosedLoopSim(assemble(scene))
    sim.frame_sink = frame_sink
    return sim.run(duration_s, progress)


def parse_sweep(text: str) -> tuple[str, list[Any]]:
    """``KEY=V1,V2,...`` -> ``(KEY, [values])``; values are read as numbers when they are."""
    key, sep, raw = text.partition("=")
    key = key.strip()
    values: list[Any] = []
    for item in raw.split(","):
        item = item.strip()
        if not item:
            continue
        try:
            values.append(float(item) if any(c in item for c in ".eE") else int(item))
        except ValueError:
            values.append({"true": True, "false": False}.get(item.lower(), item))
    if not sep or not key or not values:
        raise ConfigError(
            f"--sweep {text!r}: expected KEY=V1,V2,... (e.g. surface.speed_mps=0.5,1)"
        )
    return key, values


def sweep(
    scene: Scene,
    key: str,
    values: Sequence[Any],
    *,
    compare_paper: bool = False,
    duration_s: float | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """Run ``scene`` once per value of ``key`` (and with the paper's formulation if asked).

    Returns one entry per run: ``{"value", "formulation", "record"}``.
    """
    out: list[dict[str, Any]] = []
    formulations = [("ours", {})] + ([("paper", PAPER_OVERRIDES)] if compare_paper else [])
    for value in values:
        for name, extra in formulations:
            if progress is not None:
                progress(f"{key}={value} ({name})")
            record = run_scene(scene, {key: value, **extra}, duration_s)
            out.append({"value": value, "formulation": name, "record": record})
    return out


# ----- metrics -----------------------------------------------------------------------------------
def _angles_deg(a: FloatArray, b: FloatArray) -> FloatArray:
    cos = np.clip(np.einsum("ij,ij->i", a, b), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def estimate_errors(rec: RunRecord) -> dict[str, Any]:
    """Raw per-camera and fused estimate errors against the truth (see the module docstring)."""
    r = rec.hip_radius_m
    out: dict[str, Any] = {"near_m": NEAR_M, "cameras": {}}
    for name in rec.info["cameras"]:
        frames = [f for f in rec.frames if f.camera == name]
        near = [f for f in frames if f.true_distance_m - r < NEAR_M]
        ok = [f for f in near if f.valid]
        entry: dict[str, Any] = {
            "frames": len(frames),
            "near_frames": len(near),
            "valid_near_fraction": json_float(len(ok) / len(near)) if near else None,
            "fused_near_fraction": json_float(sum(f.admitted for f in near) / len(near))
            if near
            else None,
            "fallback_near_fraction": json_float(sum(f.fallback for f in near) / len(near))
            if near
            else None,
            "perception_ms": summary(np.array([f.perception_ms for f in frames if f.valid])),
        }
        if ok:
            c = np.array([f.centroid for f in ok])
            n = np.array([f.normal for f in ok])
            tc = np.array([f.true_point for f in ok])
            tn = np.array([f.true_normal for f in ok])
            hip = np.array([f.hip for f in ok])
            d_est = np.einsum("ij,ij->i", hip - c, n)
            d_true = np.array([f.true_distance_m for f in ok])
            entry["centroid_mm"] = summary(np.linalg.norm(c - tc, axis=1), 1e3)
            entry["normal_deg"] = summary(_angles_deg(n, tn))
            entry["d_proj_error_mm"] = summary(d_est - d_true, 1e3)
        out["cameras"][name] = entry
    a = rec.arrays
    valid = a["fused_valid"] > 0
    near = valid & (a["body_margin"] < NEAR_M)
    fused: dict[str, Any] = {"ticks": int(near.sum())}
    if near.any():
        n = a["fused_normal"][near]
        fused["centroid_mm"] = summary(
            np.linalg.norm(a["fused_centroid"][near] - a["true_point"][near], axis=1), 1e3
        )
        fused["normal_deg"] = summary(_angles_deg(n, a["true_normal"][near]))
        d_fused = np.einsum("ij,ij->i", a["hip"][near] - a["fused_centroid"][near], n) - r
        fused["d_proj_error_mm"] = summary(d_fused - a["body_margin"][near], 1e3)
    # Normal jumps between consecutive ticks that both have a valid fused surface.
    both = valid[1:] & valid[:-1]
    if both.any():
        jumps = _angles_deg(a["fused_normal"][1:][both], a["fused_normal"][:-1][both])
        fused["normal_jump_deg"] = summary(jumps)
    out["fused"] = fused
    return out


def control_stats(rec: RunRecord) -> dict[str, Any]:
    """Tick timing, deadline misses, statuses (see the module docstring)."""
    a = rec.arrays
    tick = a["tick_us"]
    codes = {code: status.value for status, code in STATUS_CODES.items()}
    statuses = {
        codes[int(c)]: int(n)
        for c, n in zip(*np.unique(a["status"], return_counts=True), strict=True)
    }
    return {
        "ticks": int(tick.size),
        "rate_hz": json_float(1.0 / rec.dt),
        "tick_us": summary(tick),
        "step_us": summary(a["step_us"]),
        "solve_us": summary(a["solve_us"]),
        "tick_without_step_us": summary(tick - a["step_us"]),
        "misses_per_10k": json_float(1e4 * float(np.count_nonzero(tick > DEADLINE_US)) / tick.size),
        "deadline_us": DEADLINE_US,
        "statuses": statuses,
        "failed_ticks": int(
            sum(
                statuses.get(s.value, 0) for s in (ControlStatus.SOLVER_FAILED, ControlStatus.FAULT)
            )
        ),
        "clamped_fraction": json_float(np.mean(a["clamped"] > 0)),
    }


def constraint_stats(rec: RunRecord) -> dict[str, Any]:
    """Fraction of ticks with rows / binding per constraint; level-4 violations."""
    a = rec.arrays
    rows = a["rows"].astype(int)
    bind = a["binding"].astype(int)
    out: dict[str, Any] = {}
    for name, bit in (("positional", POSITIONAL), ("velocity", VELOCITY), ("force", FORCE)):
        out[name] = {
            "rows_fraction": json_float(np.mean(rows & bit > 0)),
            "binding_fraction": json_float(np.mean(bind & bit > 0)),
        }
    violated = a["violation"] > 1e-6
    out["violated_fraction"] = json_float(np.mean(violated))
    out["violation_max"] = json_float(a["violation"].max()) if a["violation"].size else None
    out["surface_held_fraction"] = json_float(
        np.mean((a["nearest"] == 0) & (a["fused_valid"] == 0) & (rows > 0))
    )
    return out


def _moving_average(x: FloatArray, n: int) -> FloatArray:
    n = max(1, min(n, x.size))
    kernel = np.ones(n) / n
    pad = np.pad(x, (n // 2, n - 1 - n // 2), mode="edge")
    return np.convolve(pad, kernel, mode="valid")


def contact_stats(rec: RunRecord) -> dict[str, Any]:
    """Contact episodes: approach, penetration, rebound; jitter while in contact."""
    a = rec.arrays
    t, margin = a["t"], a["margin"]
    dt = rec.dt
    in_contact = margin < CONTACT_M
    # Relative velocity along the true normal (positive = moving away from the surface).
    rel = np.einsum("ij,ij->i", a["hip_velocity"] - a["true_velocity"], a["true_normal"])
    episodes: list[tuple[int, int]] = []
    k = 0
    gap = round(0.1 / dt)
    while k < margin.size:
        if in_contact[k]:
            start = k
            while k < margin.size and in_contact[k]:
                k += 1
            if episodes and start - episodes[-1][1] < gap:
                episodes[-1] = (episodes[-1][0], k)
            else:
                episodes.append((start, k))
        k += 1
    window = round(REBOUND_WINDOW_S / dt)
    before = round(0.3 / dt)
    out = []
    for start, end in episodes:
        # The impact: the deepest point soon after contact (later minima are the patient's
        # steady push, not the impact).
        impact_end = min(end, start + round(IMPACT_WINDOW_S / dt) + 1)
        deep = start + int(np.argmin(margin[start:impact_end]))
        after = slice(deep, min(deep + window, margin.size))
        pre = slice(max(0, start - before), start + 1)
        out.append(
            {
                "t_contact_s": json_float(t[start]),
                "t_deepest_s": json_float(t[deep]),
                "duration_s": json_float((end - start) * dt),
                "approach_speed_max_mps": json_float(max(0.0, -rel[pre].min())),
                "speed_at_contact_mps": json_float(max(0.0, -rel[start])),
                "min_margin_m": json_float(margin[start:end].min()),
                "impact_margin_m": json_float(margin[deep]),
                "penetration_m": json_float(max(0.0, -margin[start:end].min())),
                "rebound_m": json_float(margin[after].max() - margin[deep]),
                "rebound_speed_mps": json_float(max(0.0, rel[after].max())),
            }
        )
    jitter = None
    if in_contact.any():
        smooth = _moving_average(margin, round(0.1 / dt))
        jitter = json_float(np.std((margin - smooth)[in_contact]) * 1e3)
    return {"threshold_m": CONTACT_M, "episodes": out, "contact_jitter_mm": jitter}


def run_verdict(rec: RunRecord) -> Verdict:
    """SAFE or UNSAFE from the run's true margins (:mod:`.verdict`)."""
    a = rec.arrays
    return judge(a["t"], a["margin"], space=a["space"], fused_age_s=a["fused_age"])


def report(rec: RunRecord) -> dict[str, Any]:
    """The JSON report of one run (see the module docstring)."""
    a = rec.arrays
    cfg = rec.scene.config
    margin = a["margin"]
    i_min = int(np.argmin(margin)) if margin.size else 0
    min_margin = json_float(margin[i_min]) if margin.size else None
    contacts = contact_stats(rec)
    out: dict[str, Any] = {
        "scene": {
            "name": cfg.scene.name,
            "path": rec.scene.path,
            "description": cfg.scene.description,
            "duration_s": json_float(rec.n_ticks * rec.dt),
            "seed": cfg.scene.seed,
        },
        "built": rec.info,
        "feasible": True,
        "hip_radius_m": rec.hip_radius_m,
        "clearance_m": cfg.haptics.clearance_m,
        "min_margin_m": min_margin,
        "max_penetration_m": json_float(max(0.0, -margin[i_min])) if margin.size else None,
        "min_center_margin_m": json_float(margin[i_min] + rec.hip_radius_m)
        if margin.size
        else None,
        "t_min_margin_s": json_float(a["t"][i_min]) if margin.size else None,
        "estimates": estimate_errors(rec) if rec.info["cameras"] else None,
        "control": control_stats(rec),
        "constraints": constraint_stats(rec),
        "contacts": contacts["episodes"],
        "contact_jitter_mm": contacts["contact_jitter_mm"],
        "wall_time_s": json_float(rec.wall_time_s),
        "wall_time_split_s": {k: json_float(v) for k, v in rec.timing_s.items()},
    }
    verdict = run_verdict(rec)
    out["verdict"] = verdict.label
    out["truth"] = {
        "min_margin_m": min_margin,
        "t_min_margin_s": out["t_min_margin_s"],
        **verdict.to_json(),
    }
    out["space"] = (
        space_summary(a["t"], a["space"], rec.info.get("space_transitions", ()), rec.dt)
        if rec.info["cameras"]
        else None
    )
    if rec.scene.has_surface:
        out["surface"] = {
            "speed_mps": cfg.surface.speed_mps,
            "start_gap_m": cfg.surface.start_gap_m,
            "travel_m": cfg.surface.travel_m,
            "start_s": cfg.surface.start_s,
            "formulation": "ours"
            if cfg.haptics.velocity.surface_velocity_feedforward
            or cfg.haptics.positional.surface_velocity_feedforward
            else "paper",
        }
    return out


def sweep_report(key: str, runs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Summary of :func:`sweep`: one row per (value, formulation), plus each run's report."""
    rows = []
    reports = []
    for run in runs:
        rep = report(run["record"])
        reports.append({"value": run["value"], "formulation": run["formulation"], "report": rep})
        rows.append(
            {
                "value": run["value"],
                "formulation": run["formulation"],
                "min_margin_m": rep["min_margin_m"],
                "min_center_margin_m": rep["min_center_margin_m"],
                "max_penetration_m": rep["max_penetration_m"],
                "wall_time_s": rep["wall_time_s"],
                "verdict": rep["verdict"],
                "verdict_line": rep["truth"]["line"],
            }
        )
    return {"key": key, "rows": rows, "runs": reports}


def summary_lines(rep: Mapping[str, Any]) -> list[str]:
    """A few human-readable lines of a report (what ``hapticloud run`` prints)."""

    def mm(x: float | None) -> str:
        return "n/a" if x is None else f"{x * 1e3:+.1f} mm"

    ctl = rep["control"]
    lines = [
        f"scene {rep['scene']['name']}: {rep['scene']['duration_s']:.2f} s simulated in "
        f"{rep['wall_time_s']:.1f} s wall time",
        f"min margin {mm(rep['min_margin_m'])} at t = {rep['t_min_margin_s']:.3f} s "
        f"(HIP radius {rep['hip_radius_m']} m; penetration {mm(rep['max_penetration_m'])})",
        f"tick median {ctl['tick_us']['median']:.0f} us, p99 {ctl['tick_us']['p99']:.0f} us, "
        f"misses {ctl['misses_per_10k']:.1f}/10k; statuses {ctl['statuses']}",
    ]
    est = rep.get("estimates")
    if est:
        for name, cam in est["cameras"].items():
            c = cam.get("centroid_mm", {}).get("median")
            n = cam.get("normal_deg", {}).get("median")
            lines.append(
                f"camera {name}: centroid {c if c is None else round(c, 2)} mm, normal "
                f"{n if n is None else round(n, 2)} deg (median, near frames)"
            )
        fz = est["fused"]
        if "centroid_mm" in fz:
            lines.append(
                f"fused: centroid {fz['centroid_mm']['median']:.2f} mm, normal "
                f"{fz['normal_deg']['median']:.2f} deg (median), max normal jump "
                f"{fz['normal_jump_deg']['max']:.2f} deg/tick"
            )
    for ep in rep["contacts"]:
        lines.append(
            f"contact at {ep['t_contact_s']:.2f} s: approach {ep['approach_speed_max_mps']:.2f} "
            f"m/s, at contact {ep['speed_at_contact_mps']:.2f} m/s, min margin "
            f"{mm(ep['min_margin_m'])}, rebound {ep['rebound_m'] * 1e3:.1f} mm at "
            f"{ep['rebound_speed_mps']:.2f} m/s"
        )
    space = rep.get("space")
    if space:
        share = space["fraction"]
        lines.append(
            f"space: known {share['known']:.0%}, holding {share['holding']:.0%}, stopped "
            f"{share['stopped']:.0%} of the run "
            f"(longest unknown {space['longest_unknown_s']:.2f} s)"
        )
    lines.append(rep["truth"]["line"])
    return lines


__all__ = [
    "CONTACT_M",
    "NEAR_M",
    "PAPER_OVERRIDES",
    "contact_stats",
    "control_stats",
    "estimate_errors",
    "parse_sweep",
    "report",
    "run_scene",
    "summary_lines",
    "sweep",
    "sweep_report",
]
