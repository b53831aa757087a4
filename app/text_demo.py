"""A text view of the simulated demo: one line per camera frame, paced at the camera rate."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any, TextIO

import numpy as np
from hapticloud.core.studies.demo import demo_frames
from hapticloud.core.studies.verdict import judge_estimates

HEADER = (
    "    t s  camera   valid  body            d_proj mm (true)   centroid err mm  "
    "normal err deg  latency ms"
)


def format_frame(f: Any) -> str:
    est = f.estimate
    if est.valid:
        tail = (
            f"{1e3 * f.d_proj_m:7.1f} ({1e3 * f.d_proj_true_m:6.1f})   {f.centroid_error_mm:10.2f}"
            f"   {f.normal_error_deg:12.2f}   {f.latency_ms:9.2f}"
        )
    else:
        tail = f"   -- ({1e3 * f.d_proj_true_m:6.1f})   invalid: {est.reason}"
    valid = "yes" if est.valid else "no"
    return f"{f.t:7.3f}  {est.camera:8s} {valid:5s}  {f.truth.body:14s}  {tail}"


def run_text_demo(
    duration_s: float,
    overrides: Mapping[str, Any] | None = None,
    realtime: bool = True,
    out: TextIO | None = None,
    record: str | None = None,
) -> int:
    """Print the demo's estimates against ground truth; returns the exit code. ``record``: also
    record the frames and estimates to this ``.mcap`` file."""
    if record is not None:
        from hapticloud.core.studies.perception import perception_config
        from hapticloud.hardware.recording.runs import (
            demo_recorder,
            frame_hook,
            recording_summary,
        )

        recorder = demo_recorder(record, perception_config(overrides))
        try:
            code = _run(duration_s, overrides, realtime, out, frame_hook(recorder.sink))
        finally:
            result = recorder.close()
        print(recording_summary(result), file=out, flush=True)
        return code
    return _run(duration_s, overrides, realtime, out, None)


def _run(
    duration_s: float,
    overrides: Mapping[str, Any] | None,
    realtime: bool,
    out: TextIO | None,
    frame_sink: Any,
) -> int:
    print(HEADER, file=out, flush=True)
    start = time.monotonic()
    errors = []
    judged: list[tuple[float, float, float]] = []
    for frame in demo_frames(duration_s, overrides, frame_sink=frame_sink):
        if realtime:
            delay = start + frame.t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        print(format_frame(frame), file=out, flush=True)
        if not math.isnan(frame.centroid_error_mm):
            errors.append(frame.centroid_error_mm)
        if frame.estimate.valid:
            judged.append((frame.t, frame.d_proj_m, frame.d_proj_true_m))
    if errors:
        errors.sort()
        median = errors[len(errors) // 2]
        print(f"{len(errors)} valid estimates, median centroid error {median:.2f} mm", file=out)
    t, d_est, d_true = (
        (np.array(c, dtype=np.float64) for c in zip(*judged, strict=True))
        if (judged)
        else (np.zeros(0),) * 3
    )
    # No robot moves in this demo, so there is no margin to judge, only how far the estimates
    # erred on the unsafe side (the surface reported farther than it is): said, exit 0.
    check = judge_estimates(t, d_est, d_true)
    if check.min_margin_m is None:
        print("estimates: none valid to check against the truth", file=out, flush=True)
        return 0
    optimistic = int(np.count_nonzero(d_est - d_true > check.allowed_penetration_m))
    print(
        f"estimates: at worst {-check.min_margin_m * 1e3:+.1f} mm farther than the true surface "
        f"(t={check.t_min_s:.2f} s); {optimistic} of {len(judged)} valid estimates more than "
        f"{check.allowed_penetration_m * 1e3:.0f} mm on that side",
        file=out,
        flush=True,
    )
    return 0
