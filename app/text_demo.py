"""A text view of the simulated demo: one line per camera frame, paced at the camera rate."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any, TextIO

from hapticloud.core.studies.demo import demo_frames

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
) -> int:
    """Print the demo's estimates against ground truth; returns the exit code."""
    print(HEADER, file=out, flush=True)
    start = time.monotonic()
    errors = []
    for frame in demo_frames(duration_s, overrides):
        if realtime:
            delay = start + frame.t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        print(format_frame(frame), file=out, flush=True)
        if not math.isnan(frame.centroid_error_mm):
            errors.append(frame.centroid_error_mm)
    if errors:
        errors.sort()
        median = errors[len(errors) // 2]
        print(f"{len(errors)} valid estimates, median centroid error {median:.2f} mm", file=out)
    return 0
