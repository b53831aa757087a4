"""``hapticloud bench record``: what recording costs a real-time session, and how fast replay is.

The same scene runs twice through the hardware layer (:func:`~..session.run.run_session`), without
and with ``--record``; the figures: control deadline misses per 10,000 ticks of each (the issue's
bound: with recording at most 1 per 10k more), the recorder process's CPU time over the
session's duration (% of one core; bound 15 %), the file's size and rate, messages dropped at the
queue, and the replay's speed on the recording (recorded time / wall time; bound 2x).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any


def record_bench(
    scene: str = "impacts",
    duration_s: float = 10.0,
    overrides: Mapping[str, Any] | None = None,
    keep: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the study (see the module docstring); ``keep``: where to leave the recording."""
    from hapticloud.core.recording import replay, replay_configs

    from ..session.run import run_session
    from .reader import Recording

    say = progress or (lambda _text: None)
    ovr = dict(overrides) if overrides else None
    with tempfile.TemporaryDirectory() as tmp:
        path = keep or str(Path(tmp) / "bench.mcap")
        say(f"{scene}: {duration_s:g} s without recording ...")
        plain = run_session(scene, ovr, duration_s)
        say(f"{scene}: {duration_s:g} s with --record {path} ...")
        recorded = run_session(scene, ovr, duration_s, record=path)
        rec_result = recorded["recording"]
        say("replaying the recording ...")
        with Recording.open(path) as rec:
            perception, fusion = replay_configs(rec.config_toml())
            estimates = {(e.camera, e.seq): e for e in rec.estimates()}
            frames = list(rec.frames())
            span = rec.duration_s
            size = Path(path).stat().st_size
        wall0 = time.perf_counter()
        result = replay(frames, estimates, perception, fusion)
        replay_s = time.perf_counter() - wall0
    summary = result.summary()
    return {
        "scene": scene,
        "duration_s": duration_s,
        "misses_per_10k_without": plain["control"]["misses_per_10k"],
        "misses_per_10k_with": recorded["control"]["misses_per_10k"],
        "recorder_cpu_s": rec_result.get("cpu_s"),
        "recorder_core_percent": 100.0 * rec_result.get("cpu_s", 0.0) / duration_s,
        "file_mb": size / 1e6,
        "mb_per_s": size / 1e6 / max(span, 1e-9),
        "messages": rec_result.get("messages"),
        "dropped": rec_result.get("dropped"),
        "recording_error": rec_result.get("error") or None,
        "frames": summary["frames"],
        "replay_wall_s": replay_s,
        "replay_real_time_factor": span / replay_s if replay_s > 0 else None,
        "replay_identical": summary["identical"],
        "replay_with_recorded_estimate": summary["with_recorded_estimate"],
        "replay_max_centroid_diff_mm": summary["max_centroid_diff_mm"],
    }


def bench_lines(r: Mapping[str, Any]) -> list[str]:
    """The study's result as a few lines."""
    return [
        f"{r['scene']}, {r['duration_s']:g} s through the hardware layer:",
        f"  control misses per 10k: {r['misses_per_10k_without'] or 0:.1f} without recording, "
        f"{r['misses_per_10k_with'] or 0:.1f} with",
        f"  recorder process: {r['recorder_cpu_s'] or 0:.2f} s CPU = "
        f"{r['recorder_core_percent']:.1f} % of one core; {r['file_mb']:.1f} MB "
        f"({r['mb_per_s']:.2f} MB/s), {r['messages']} messages, {r['dropped']} dropped"
        + (f"; {r['recording_error']}" if r["recording_error"] else ""),
        f"  replay: {r['frames']} frames in {r['replay_wall_s']:.2f} s = "
        f"{r['replay_real_time_factor'] or 0:.1f}x real time; identical "
        f"{r['replay_identical']} of {r['replay_with_recorded_estimate']}, max_centroid_diff_mm "
        f"{r['replay_max_centroid_diff_mm']}",
    ]


__all__ = ["bench_lines", "record_bench"]
