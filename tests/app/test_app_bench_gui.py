"""``hapticloud bench gui``: runs without a display (its own Xvfb) and prints the figures as JSON.

A short run (1 s) checks the command and its JSON, not the rate: the measured figures are in
docs/benchmarks.md (``hapticloud bench gui --duration 10 --json``).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
KEYS = (
    "updates_per_s",
    "update_ms_median",
    "render_ms_median",
    "frame_to_screen_ms_median",
    "frame_to_screen_ms_p90",
    "actors_added",
    "control_alone_misses_per_10k",
    "control_gui_misses_per_10k",
    "control_alone_ticks",
    "control_gui_ticks",
)


def test_bench_gui_json_without_a_display() -> None:
    pytest.importorskip("PyQt6", reason="the app extras are not installed")
    pytest.importorskip("pyvista", reason="the app extras are not installed")
    if shutil.which("Xvfb") is None:
        pytest.skip("no Xvfb to start a display (apt-get install xvfb)")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env.pop("QT_QPA_PLATFORM", None)
    proc = subprocess.run(
        [sys.executable, "-m", "hapticloud.app.cli", "bench", "gui", "--duration", "1", "--json"],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stdout.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stdout
    result = json.loads(lines[0])
    for key in KEYS:
        assert key in result, key
        assert isinstance(result[key], int | float), (key, result[key])
    assert result["actors_added"] == 0
    assert result["control_alone_ticks"] > 0 and result["control_gui_ticks"] > 0
    assert result["updates_per_s"] > 0
    assert result["update_ms_median"] > 0 and result["render_ms_median"] > 0
    assert result["frame_to_screen_ms_p90"] >= result["frame_to_screen_ms_median"] > 0
