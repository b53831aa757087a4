"""The paper's figures from closed-loop runs, as PNG files (matplotlib, Agg: no display needed).

- :func:`fig8_fusion`: the raw 30 Hz estimates of each camera, the regression's 800 Hz target
  trajectory and the PID follower's output, against the truth (centroid and normal components);
- :func:`fig11_distance_velocity`: the free distance ``d_proj`` and its rate over time, with the
  constraints' activity shaded;
- :func:`fig12_speed_sweep`: the margin over time for each surface speed, and the smallest margin
  against the speed, ours against the paper's formulation.

Views only: every number comes from the run's record (:class:`~hapticloud.core.sim.closed_loop.
RunRecord`) or from :mod:`hapticloud.core.studies.run`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from hapticloud.core.loop import POSITIONAL, VELOCITY
from hapticloud.core.sim.closed_loop import RunRecord

_CAMERA_COLOURS = ("tab:orange", "tab:green", "tab:purple", "tab:brown")
_DPI = 130


def _time_window(rec: RunRecord) -> tuple[float, float]:
    """The span where the fused surface exists (the whole run without one)."""
    a = rec.arrays
    valid = np.flatnonzero(a["fused_valid"] > 0)
    if valid.size == 0:
        return float(a["t"][0]), float(a["t"][-1])
    return float(a["t"][valid[0]]), float(a["t"][valid[-1]])


def fig8_fusion(rec: RunRecord, path: str | Path) -> Path:
    """Raw estimates (30 Hz per camera), regression target and PID output (800 Hz), truth."""
    a = rec.arrays
    t = a["t"]
    t0, t1 = _time_window(rec)
    sel = (t >= t0) & (t <= t1)
    valid = sel & (a["fused_valid"] > 0)
    fig, axes = plt.subplots(2, 3, figsize=(14, 7), sharex=True)
    for row, (title, key_out, key_target, key_true, frame_key, unit, scale) in enumerate(
        (
            ("centroid", "fused_centroid", "target_centroid", "true_point", "centroid", "m", 1.0),
            ("normal", "fused_normal", "target_normal", "true_normal", "normal", "", 1.0),
        )
    ):
        for col, axis_name in enumerate("xyz"):
            ax = axes[row, col]
            for k, cam in enumerate(rec.info["cameras"]):
                frames = [f for f in rec.frames if f.camera == cam and f.valid and t0 <= f.t <= t1]
                if not frames:
                    continue
                ft = np.array([f.t for f in frames])
                fv = np.array([getattr(f, frame_key)[col] for f in frames]) * scale
                used = np.array([f.admitted for f in frames])
                colour = _CAMERA_COLOURS[k % len(_CAMERA_COLOURS)]
                ax.scatter(ft[used], fv[used], s=12, color=colour, label=f"raw {cam} (fused)")
                if (~used).any():
                    ax.scatter(
                        ft[~used],
                        fv[~used],
                        s=14,
                        marker="x",
                        color=colour,
                        alpha=0.6,
                        label=f"raw {cam} (rejected)",
                    )
            truth = np.where(valid, a[key_true][:, col] * scale, np.nan)
            target = np.where(valid, a[key_target][:, col] * scale, np.nan)
            output = np.where(valid, a[key_out][:, col] * scale, np.nan)
            ax.plot(t, truth, "k--", lw=1.0, label="truth")
            ax.plot(t, target, color="tab:blue", lw=0.8, alpha=0.8, label="regression (800 Hz)")
            ax.plot(t, output, color="tab:red", lw=1.4, label="PID output (800 Hz)")
            ax.set_title(f"{title} {axis_name}" + (f" ({unit})" if unit else ""))
            ax.grid(alpha=0.3)
            if row == 1:
                ax.set_xlabel("t (s)")
            ax.set_xlim(t0, t1)
            _robust_ylim(ax, truth)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), fontsize=9)
    fig.suptitle(
        f"Fig. 8 — {rec.scene.name}: raw estimates, regression target and PID output",
        fontsize=12,
    )
    fig.tight_layout(rect=(0, 0.06, 1, 0.96))
    return _save(fig, path)


def _robust_ylim(ax: Any, truth: np.ndarray) -> None:
    """Keep the axis on the truth's range (plus margin) so outliers do not flatten the curves."""
    v = truth[np.isfinite(truth)]
    if v.size == 0:
        return
    lo, hi = float(v.min()), float(v.max())
    pad = max(0.25 * (hi - lo), 0.02)
    ax.set_ylim(lo - pad, hi + pad)


def _shade(ax: Any, t: np.ndarray, mask: np.ndarray, colour: str, label: str) -> None:
    if not mask.any():
        return
    edges = np.flatnonzero(np.diff(np.concatenate(([0], mask.astype(int), [0]))))
    first = True
    for start, end in zip(edges[::2], edges[1::2], strict=True):
        ax.axvspan(
            t[start],
            t[min(end, t.size - 1)],
            color=colour,
            alpha=0.25,
            lw=0,
            label=label if first else None,
        )
        first = False


def fig11_distance_velocity(rec: RunRecord, path: str | Path) -> Path:
    """``d_proj`` (true and as the controller saw it) and its rate, constraint activity shaded."""
    a = rec.arrays
    t = a["t"]
    margin = a["margin"] * 1e3
    seen = np.where(np.isfinite(a["d_proj"]), a["d_proj"] * 1e3, np.nan)
    rel = np.einsum("ij,ij->i", a["hip_velocity"] - a["true_velocity"], a["true_normal"])
    rows = a["rows"].astype(int)
    binding = a["binding"].astype(int)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(12, 7), sharex=True)
    for ax in (ax1, ax2):
        _shade(ax, t, (rows & (POSITIONAL | VELOCITY)) > 0, "0.85", "constraint rows")
        _shade(ax, t, (binding & POSITIONAL) > 0, "tab:red", "positional binding")
        _shade(ax, t, (binding & VELOCITY) > 0, "tab:blue", "velocity binding")
    ax1.plot(t, margin, "k", lw=1.3, label="true d_proj (HIP sphere)")
    ax1.plot(t, seen, color="tab:orange", lw=0.9, alpha=0.9, label="d_proj the controller used")
    ax1.axhline(0.0, color="tab:red", lw=0.8, ls="--")
    ax1.set_ylabel("d_proj (mm)")
    ax1.grid(alpha=0.3)
    finite = margin[np.isfinite(margin)]
    if finite.size:
        top = min(float(np.percentile(finite, 99)), 250.0)
        ax1.set_ylim(min(-5.0, float(finite.min()) - 2.0), max(top, 20.0))
    ax1.legend(loc="upper right", fontsize=8, ncol=2)
    ax2.plot(t, rel, "k", lw=1.2, label="d/dt d_proj (true, relative to the surface)")
    ax2.axhline(0.0, color="0.4", lw=0.8)
    ax2.set_ylabel("velocity (m/s)")
    ax2.set_xlabel("t (s)")
    ax2.grid(alpha=0.3)
    ax2.legend(loc="upper right", fontsize=8)
    fig.suptitle(
        f"Fig. 11 — {rec.scene.name}: free distance and its rate "
        f"(min margin {margin.min():+.2f} mm)",
        fontsize=12,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    return _save(fig, path)


def fig12_speed_sweep(
    key: str, runs: Sequence[Mapping[str, Any]], rows: Sequence[Mapping[str, Any]], path: str | Path
) -> Path:
    """Margin over time per speed (ours solid, paper dashed) and the smallest margin per speed."""
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(14, 5.5), gridspec_kw={"width_ratios": [3, 2]})
    values = sorted({r["value"] for r in runs})
    cmap = plt.get_cmap("viridis")
    colour = {v: cmap(i / max(len(values) - 1, 1)) for i, v in enumerate(values)}
    for run in runs:
        rec: RunRecord = run["record"]
        a = rec.arrays
        ls = "-" if run["formulation"] == "ours" else "--"
        ax1.plot(
            a["t"],
            a["margin"] * 1e3,
            ls=ls,
            color=colour[run["value"]],
            lw=1.2,
            label=f"{run['value']} ({run['formulation']})",
        )
    r_hip = runs[0]["record"].hip_radius_m * 1e3 if runs else 40.0
    ax1.axhline(0.0, color="tab:red", lw=0.8)
    ax1.axhline(-r_hip, color="tab:red", lw=0.8, ls=":")
    ax1.set_ylim(-r_hip - 25.0, 320.0)
    ax1.set_xlabel("t (s)")
    ax1.set_ylabel("true margin of the HIP sphere (mm)")
    ax1.set_title(f"margin over time per {key} (solid ours, dashed paper)")
    ax1.grid(alpha=0.3)
    ax1.legend(fontsize=7, ncol=2, loc="upper right")
    for form, marker in (("ours", "o"), ("paper", "s")):
        pts = sorted((r["value"], r["min_margin_m"]) for r in rows if r["formulation"] == form)
        if pts:
            xs, ys = zip(*pts, strict=True)
            ax2.plot(xs, np.array(ys) * 1e3, marker=marker, lw=1.5, label=form)
    ax2.axhline(0.0, color="tab:red", lw=0.8, label="HIP sphere touches")
    ax2.axhline(-r_hip, color="tab:red", lw=0.8, ls=":", label="HIP centre touches")
    ax2.set_xlabel(key)
    ax2.set_ylabel("smallest margin over the run (mm)")
    ax2.set_title("smallest margin against the surface speed")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8)
    fig.suptitle("Fig. 12 — moving surface: margin against speed", fontsize=12)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return _save(fig, path)


def _save(fig: Any, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=_DPI)
    plt.close(fig)
    return path


__all__ = ["fig8_fusion", "fig11_distance_velocity", "fig12_speed_sweep"]
