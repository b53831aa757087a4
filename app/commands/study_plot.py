"""The figures of ``hapticloud study --plot``: the front, and one plot per knob."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

LAT, ERR = "latency_ms_median", "centroid_mm_p90"


def _figure(*args: Any, **kwargs: Any) -> Any:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    return plt.subplots(*args, **kwargs)


def _xy(trials: Sequence[Any], indices: Sequence[int]) -> tuple[list[float], list[float]]:
    ok = [
        i for i in indices if math.isfinite(trials[i].objectives[LAT] + trials[i].objectives[ERR])
    ]
    return [trials[i].objectives[LAT] for i in ok], [trials[i].objectives[ERR] for i in ok]


def plot_front(
    path: Path,
    trials: Sequence[Any],
    front: Sequence[int],
    default_index: int | None,
    presets: Mapping[str, int],
    command: str,
    objectives: str,
) -> None:
    """Latency (x) against the p90 centroid error (y, log): dominated trials grey, unsafe red,
    the front blue, the shipped default and the presets marked."""
    fig, ax = _figure(figsize=(8, 5.5), dpi=110)
    dominated = [i for i, t in enumerate(trials) if i not in front and not t.unsafe]
    unsafe = [i for i, t in enumerate(trials) if t.unsafe]
    ax.scatter(*_xy(trials, dominated), s=18, color="0.7", label="dominated")
    if unsafe:
        ax.scatter(*_xy(trials, unsafe), s=22, color="tab:red", marker="x", label="unsafe")
    # The front is over more figures than the two drawn: a blue point may sit above-right of
    # another and still win on the centroid median or |d_proj|.
    xs, ys = _xy(trials, front)
    ax.scatter(xs, ys, s=34, color="tab:blue", zorder=3, label="non-dominated (" + objectives + ")")
    if default_index is not None:
        dx, dy = _xy(trials, [default_index])
        ax.scatter(dx, dy, s=160, marker="*", color="tab:orange", zorder=4, label="shipped default")
    for name, i in presets.items():
        px, py = _xy(trials, [i])
        if px:
            ax.annotate(name, (px[0], py[0]), textcoords="offset points", xytext=(6, 6))
    ax.set_yscale("log")
    ax.set_xlabel("latency from the depth frame, median (ms)")
    ax.set_ylabel("centroid error vs truth, p90 (mm)")
    ax.set_title("speed/accuracy trade: lower left is better", fontsize=11)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    fig.text(0.01, 0.01, command, fontsize=6, color="0.4")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    fig.savefig(path)
    _close(fig)


def plot_knobs(
    folder: Path, trials: Sequence[Any], front: Sequence[int], keys: Sequence[str]
) -> None:
    """Per knob: its value against the p90 centroid error and the latency (front in blue)."""
    for key in keys:
        fig, (top, bottom) = _figure(2, 1, figsize=(6, 5), dpi=100, sharex=True)
        for axis, name, label in (
            (top, ERR, "centroid p90 (mm)"),
            (bottom, LAT, "latency median (ms)"),
        ):
            for group, colour in (
                ([i for i in range(len(trials)) if i not in front], "0.7"),
                (list(front), "tab:blue"),
            ):
                pts = [
                    (trials[i].params[key], trials[i].objectives[name])
                    for i in group
                    if key in trials[i].params
                    and math.isfinite(trials[i].objectives[name])
                    and not isinstance(trials[i].params[key], str)
                ]
                if pts:
                    axis.scatter(*zip(*pts, strict=True), s=14, color=colour)
            axis.set_ylabel(label)
            axis.grid(True, alpha=0.3)
        bottom.set_xlabel(key)
        top.set_title(key, fontsize=10)
        fig.tight_layout()
        fig.savefig(folder / f"knob_{key.replace('.', '_')}.png")
        _close(fig)


def _close(fig: Any) -> None:
    from matplotlib import pyplot as plt

    plt.close(fig)
