"""``hapticloud run`` and ``hapticloud bench loop`` from the command line: exit codes, reports."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hapticloud.app.cli import main

WALL = """
[scene]
name = "cli-wall"
duration_s = 0.4

[robot]
hip0_m = [0.30, 0.10, 1.00]

[[walls]]
name = "floor"
point_m = [0.3, 0.1, 0.90]
normal = [0.0, 0.0, 1.0]

[patient]

[[patient.waypoints]]
position_m = [0.0, 0.0, 0.0]

[[patient.waypoints]]
position_m = [0.0, 0.0, -0.12]
speed_mps = 0.5
profile = "linear"
"""


def _scene(tmp_path: Path, text: str = WALL) -> Path:
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


def test_run_writes_the_report_with_the_required_keys(tmp_path: Path, capsys) -> None:
    report = tmp_path / "out" / "report.json"
    code = main(["run", str(_scene(tmp_path)), "--report", str(report)])
    assert code == 0
    rep = json.loads(report.read_text())
    for key in (
        "min_margin_m",
        "max_penetration_m",
        "control",
        "constraints",
        "contacts",
        "estimates",
        "wall_time_s",
    ):
        assert key in rep
    assert rep["estimates"] is None  # no cameras: no perception, nothing to compare
    assert rep["built"]["perception"] is False and rep["built"]["fusion"] is False
    assert rep["min_margin_m"] >= 0.0  # pushed 2 cm "into" the plane, held out of it
    assert rep["control"]["tick_us"]["median"] > 0
    assert "min margin" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv_tail", "needle"),
    [
        (["--duration", "-1"], "must be a positive number"),
        (["--duration", "abc"], "expected a number"),
        (["--set", "robot.hip_radius_m=9"], "robot.hip_radius_m = 9"),
        (["--set", "robot.bogus=1"], "robot.bogus: unknown key"),
        (["--set", "nonsense"], "expected section.key=value"),
        (["--compare-paper"], "needs --sweep"),
    ],
)
def test_bad_input_exits_2_with_one_line(tmp_path: Path, capsys, argv_tail, needle) -> None:
    with pytest.raises(SystemExit) as info:
        code = main(["run", str(_scene(tmp_path)), *argv_tail])
        raise SystemExit(code)
    assert info.value.code == 2
    # The reason is one line (argparse prints its usage before it).
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert needle in last


def test_bad_scene_file_exits_2_naming_the_key(tmp_path: Path, capsys) -> None:
    path = _scene(tmp_path, WALL.replace("[robot]", "[robot]\nhip_radius = 0.04"))
    assert main(["run", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(path) in err and "robot.hip_radius: unknown key" in err
    assert main(["run", str(tmp_path / "missing.toml")]) == 2


def test_infeasible_scene_is_reported_not_crashed(tmp_path: Path, capsys) -> None:
    path = _scene(tmp_path, WALL.replace("[0.30, 0.10, 1.00]", "[1.2, 0.0, 1.0]"))
    report = tmp_path / "r.json"
    assert main(["run", str(path), "--report", str(report)]) == 2
    assert json.loads(report.read_text())["feasible"] is False
    assert "infeasible" in capsys.readouterr().err


def test_sweep_runs_each_value(tmp_path: Path) -> None:
    report = tmp_path / "sweep.json"
    code = main(
        [
            "run",
            str(_scene(tmp_path)),
            "--duration",
            "0.1",
            "--sweep",
            "patient.stiffness_n_per_m=100,300",
            "--quiet",
            "--report",
            str(report),
        ]
    )
    assert code == 0
    rows = json.loads(report.read_text())["rows"]
    assert [r["value"] for r in rows] == [100, 300]


def test_bench_loop_prints_one_json_object(capsys) -> None:
    assert main(["bench", "loop", "--duration", "0.2", "--scene", "wall", "--json"]) == 0
    out = capsys.readouterr().out.strip()
    result = json.loads(out)
    for key in ("tick_us_median", "tick_us_p99", "misses_per_10k"):
        assert result[key] >= 0.0
    # The controller's cost on the ticks that solve, apart from the (mostly skipping) others.
    assert 0.0 <= result["solving_fraction"] <= 1.0
    solving = result["controller_step_us_median_solving"]
    assert (solving is None) == (result["solving_fraction"] == 0.0)
    assert (result["solve_us_median_solving"] is None) == (solving is None)
