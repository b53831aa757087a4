"""``hapticloud app``: the command line, and ``--screenshot`` writing a PNG with the 3D view."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hapticloud.app import cli
from hapticloud.core.scene import load_scene

ROOT = Path(__file__).resolve().parents[2]


def _run(*args: str, env: dict[str, str] | None = None, timeout: float = 90.0):
    return subprocess.run(
        [sys.executable, "-m", "hapticloud.app.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        cwd=ROOT,
    )


def test_app_is_the_default_command_and_demo_stays() -> None:
    assert cli.DEFAULT_COMMAND == ["app"]
    assert "app" in cli.COMMANDS and "demo" in cli.COMMANDS
    parser = cli.build_parser()
    args = parser.parse_args(cli.DEFAULT_COMMAND)
    assert args.command == "app" and args.scene == "demo"


@pytest.mark.parametrize(
    ("argv", "reason"),
    [
        (["app", "nowhere"], "nowhere: no such scene file (built-in scenes: demo"),
        (["app", "scene.toml"], "scene.toml: no such scene file"),
        (["app", "--set", "perception.voxel.voxel_size_m=-1"], "must be in [0.0005, 0.05] m"),
        (["app", "--set", "fusion.nope=1"], "unknown key"),
        (["app", "--preset", "/nonexistent.toml"], "no such file"),
    ],
)
def test_bad_input_exits_2_with_a_one_line_reason(argv, reason, capsys) -> None:
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert reason in err and len(err.splitlines()) == 1


def test_no_display_without_screenshot_is_refused(monkeypatch, capsys) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert cli.main(["app"]) == 2
    assert "no display" in capsys.readouterr().err


def test_screenshot_writes_a_png_with_the_3d_view(tmp_path: Path, gui_display: str) -> None:
    from hapticloud.app.scene_view import BACKGROUND
    from hapticloud.app.screenshot import qimage_to_array
    from PyQt6 import QtGui

    png = tmp_path / "window.png"
    report = tmp_path / "report.json"
    # No DISPLAY: the command starts its own virtual display (what CI and docs builds need).
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    result = _run(
        "app",
        "--screenshot",
        str(png),
        "--report",
        str(report),
        "--exit-after",
        "6",
        "--size",
        "1280x800",
        "--decimation",
        "2",
        env=env,
    )
    assert result.returncode == 0, result.stderr
    assert f"screenshot: {png}" in result.stdout
    _check_report(json.loads(report.read_text()), result.stdout)
    image = QtGui.QImage(str(png))
    assert (image.width(), image.height()) == (1280, 800)
    rgb = qimage_to_array(image)
    # The 3D view is the large region with the view's gradient background in it: find pixels of
    # the background's top colour, and check the view shows more than background there.
    top = np.array([int(BACKGROUND[1][i : i + 2], 16) for i in (1, 3, 5)])
    bg = np.abs(rgb.astype(int) - top).max(axis=2) < 6
    rows, cols = np.nonzero(bg)
    assert len(rows) > 5000, "no 3D view background in the screenshot"
    view = rgb[rows.min() : rows.max() + 1, cols.min() : cols.max() + 1]
    # The demo starts with the patient in reach: the torso fills part of the view, so the
    # background spans less of its width than the 800 px view itself.
    assert view.shape[0] > 300 and view.shape[1] > 300
    assert view.std() > 20
    assert len(np.unique(view.reshape(-1, 3) // 8, axis=0)) > 100


def _check_report(rep: dict, stdout: str) -> None:
    """The report's fields exist and are computed from what ran (the thresholds are the
    benchmark's, not this test's)."""
    session = rep["session"]
    states = [state for _, state in session["states"]]
    # How far the session gets in 6 s depends on the machine's day: the states are its own.
    assert states[0] == "starting" and set(states) <= {"starting", "ready", "enabled"}, states
    assert all(t >= 0 for t, _ in session["states"]) and isinstance(session["faults"], list)
    if len(states) > 1:  # the control process reported: its misses are in
        assert session["misses_per_10k"] is not None and session["misses_per_10k"] >= 0
    assert set(rep["cameras"]) == {c.name for c in load_scene("demo").cameras}
    assert all(0 < cam["rate_hz_median"] < 100 for cam in rep["cameras"].values())
    assert 0 < rep["sim"]["real_time_factor_median"] < 10
    assert rep["view"]["fps_median"] > 0 and rep["view"]["frame_to_screen_ms_median"] > 0
    assert set(rep["fused_error_mm"]) >= {"n", "median", "p90"}
    assert rep["verdict"] in ("SAFE", "UNSAFE") and rep["truth"]["min_margin_m"] is not None
    assert rep["truth"]["line"] in stdout


@pytest.mark.parametrize(
    "argv",
    [["--set", "perception.voxel.voxel_size_m=-1"], ["nowhere"]],
    ids=["option-first", "scene-first"],
)
def test_arguments_without_a_command_go_to_the_app(argv, capsys) -> None:
    # `hapticloud [app] [SCENE] [options]`: the same one-line refusal as with `app` spelled out.
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert cli.main(["app", *argv]) == 2
    assert capsys.readouterr().err.strip() == err and "invalid choice" not in err
