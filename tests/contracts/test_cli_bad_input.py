"""Bad input to the command line: exit code 2 and one line naming the option or file, checked
before any run starts (a long run is never thrown away at its end)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hapticloud.app import cli
from hapticloud.app.commands import check_outputs, reason
from hapticloud.core.errors import ConfigError
from hapticloud.core.limits import BENCH_FRAMES_MAX, BENCH_FRAMES_MIN, MAX_DURATION_S

WALL = """
[scene]
name = "bad-input"
duration_s = 0.2

[robot]
hip0_m = [0.30, 0.10, 1.00]

[[walls]]
name = "floor"
point_m = [0.3, 0.1, 0.90]
normal = [0.0, 0.0, 1.0]
"""


def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI in-process; it must exit 2 with exactly one line on stderr (returned)."""
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith("hapticloud: error: ")
    return err


@pytest.fixture
def no_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any run started is a failure: the checks must refuse before it."""
    from hapticloud.core.studies import loop_bench, perception, run
    from hapticloud.hardware.control import bench
    from hapticloud.hardware.live import scenes
    from hapticloud.hardware.session import run as session

    def started(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("a run started before its arguments were checked")

    monkeypatch.setattr(run, "run_scene", started)
    monkeypatch.setattr(run, "sweep", started)
    monkeypatch.setattr(session, "run_session", started)
    monkeypatch.setattr(perception, "run_study", started)
    monkeypatch.setattr(loop_bench, "main", started)
    monkeypatch.setattr(bench, "main", started)
    monkeypatch.setattr(scenes, "scene_spec", started)


@pytest.fixture
def wall(tmp_path: Path) -> str:
    path = tmp_path / "wall.toml"
    path.write_text(WALL)
    return str(path)


# ----- 1. the duration is bounded by the scenes' limit -------------------------------------------
@pytest.mark.parametrize("value", ["700", "1e9"])
@pytest.mark.parametrize(
    "argv",
    [["run", "demo"], ["run", "impacts", "--hardware"], ["bench", "loop"]],
    ids=["run", "run-hardware", "bench-loop"],
)
def test_duration_above_the_scene_limit_is_refused(argv, value, capsys, no_runs) -> None:
    err = _refused([*argv, "--duration", value], capsys)
    assert "--duration" in err and f"at most {MAX_DURATION_S:g} s" in err


def test_the_scene_file_and_the_simulator_share_the_limit(tmp_path: Path, wall: str) -> None:
    from hapticloud.core.scene import SceneMeta, load_scene
    from hapticloud.core.sim.closed_loop import ClosedLoopSim

    hi = {p.name: p.hi for p in SceneMeta.params()}["duration_s"]
    assert hi == MAX_DURATION_S
    with pytest.raises(ConfigError, match=r"scene\.duration_s = 700\.0: must be in"):
        load_scene(wall, {"scene.duration_s": 700.0})
    with pytest.raises(ConfigError, match="at most 600 s"):
        ClosedLoopSim(load_scene(wall)).run(1e9)


# ----- 2. bench perception --frames: a stated range ----------------------------------------------
@pytest.mark.parametrize("frames", ["10", "1000000000"])
def test_bench_frames_out_of_range_is_refused_with_the_range(frames, capsys, no_runs) -> None:
    err = _refused(["bench", "perception", "--frames", frames], capsys)
    assert f"--frames = {frames}" in err
    assert f"{BENCH_FRAMES_MIN} to {BENCH_FRAMES_MAX}" in err


def test_bench_frames_help_states_the_range(capsys) -> None:
    with pytest.raises(SystemExit):
        cli.main(["bench", "perception", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert f"{BENCH_FRAMES_MIN} to {BENCH_FRAMES_MAX}" in help_text


# ----- 3. output paths are checked before the run ------------------------------------------------
@pytest.mark.parametrize(
    ("tail", "needle"),
    [
        (["run", "{wall}", "--report", "{dir}"], "--report {dir}: is a folder, expected a file"),
        (
            ["run", "{wall}", "--report", "{file}/r.json"],
            "--report {file}/r.json: {file} is a file",
        ),
        (["run", "{wall}", "--plot", "{file}"], "--plot {file}: is a file, expected a folder"),
        (["run", "{wall}", "--plot", "{file}/figs"], "--plot {file}/figs: {file} is a file"),
        (
            ["run", "{wall}", "--sweep", "patient.mass_kg=1,2", "--report", "{dir}"],
            "--report {dir}: is a folder",
        ),
        (["run", "{wall}", "--hardware", "--report", "{dir}"], "--report {dir}: is a folder"),
        (["bench", "perception", "--json", "{dir}"], "--json {dir}: is a folder"),
        (["app", "--screenshot", "{dir}"], "--screenshot {dir}: is a folder"),
    ],
    ids=[
        "report-dir",
        "report-under-file",
        "plot-file",
        "plot-under-file",
        "sweep-report-dir",
        "hardware-report-dir",
        "bench-json-dir",
        "app-screenshot-dir",
    ],
)
def test_unwritable_outputs_are_refused_before_the_run(
    tail, needle, tmp_path: Path, wall: str, capsys, no_runs
) -> None:
    names = {"wall": wall, "dir": str(tmp_path), "file": str(tmp_path / "notes.txt")}
    (tmp_path / "notes.txt").write_text("not a folder")
    err = _refused([part.format(**names) for part in tail], capsys)
    assert needle.format(**names) in err


def test_outputs_that_can_be_created_pass(tmp_path: Path) -> None:
    existing = tmp_path / "old.json"
    existing.write_text("{}")
    check_outputs(
        files={"--report": str(tmp_path / "new" / "deeper" / "r.json"), "--json": str(existing)},
        folders={"--plot": str(tmp_path / "figs" / "a"), "--other": str(tmp_path)},
    )
    check_outputs(files={"--report": None}, folders={"--plot": None})


def test_a_read_only_folder_is_refused(tmp_path: Path, monkeypatch) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    # chmod does not stop root: say the folder is read-only the way the check asks.
    monkeypatch.setattr(os, "access", lambda path, _mode: Path(path) != locked)
    with pytest.raises(ConfigError, match=f"--report {locked}/r.json: folder {locked} is not"):
        check_outputs(files={"--report": str(locked / "r.json")})
    with pytest.raises(ConfigError, match=f"--plot {locked}/figs/a: folder {locked} is not"):
        check_outputs(folders={"--plot": str(locked / "figs" / "a")})
    with pytest.raises(ConfigError, match=f"--plot {locked}: not writable$"):
        check_outputs(folders={"--plot": str(locked)})


# ----- 4. run --hardware: a reason on every failure ----------------------------------------------
def test_a_start_up_failure_names_its_cause() -> None:
    traceback_text = (
        "control process failed at start-up:\nTraceback (most recent call last):\n"
        '  File "x.py", line 1, in f\n    g()\n'
        "numpy._core._exceptions._ArrayMemoryError: Unable to allocate 5.82 TiB\n"
    )
    assert reason(RuntimeError(traceback_text)) == (
        "control process failed at start-up: "
        "numpy._core._exceptions._ArrayMemoryError: Unable to allocate 5.82 TiB"
    )
    assert reason(RuntimeError("control process failed at start-up:\n")) == (
        "control process failed at start-up: RuntimeError"
    )
    assert reason(MemoryError()) == "MemoryError"
    assert reason(TimeoutError("  \n ")) == "TimeoutError"
    assert reason(RuntimeError("one line")) == "one line"


@pytest.mark.parametrize(
    ("error", "needle"),
    [
        (RuntimeError(), "RuntimeError"),
        (RuntimeError("control process failed at start-up:\nTraceback\nMemoryError"), "Memory"),
    ],
)
def test_run_hardware_failure_is_one_nonempty_line(error, needle, monkeypatch, capsys) -> None:
    from hapticloud.hardware.session import run as session

    def fails(*_args: object, **_kwargs: object) -> None:
        raise error

    monkeypatch.setattr(session, "run_session", fails)
    assert cli.main(["run", "impacts", "--hardware", "--duration", "1"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err
    assert not err.endswith(":")


# ----- 5. an empty scene ------------------------------------------------------------------------
def test_an_empty_scene_file_is_refused(tmp_path: Path, capsys, no_runs) -> None:
    empty = tmp_path / "empty.toml"
    empty.write_text("")
    err = _refused(["run", str(empty)], capsys)
    assert f"{empty}: scene is empty: declare a [scene] table or something to touch" in err


def test_a_scene_needs_a_scene_table_or_something_to_touch(tmp_path: Path, capsys, no_runs) -> None:
    from hapticloud.core.scene import load_scene

    robot_only = tmp_path / "robot.toml"
    robot_only.write_text("[robot]\nhip0_m = [0.3, 0.1, 1.0]\n")
    err = _refused(["run", str(robot_only)], capsys)
    assert f"{robot_only}: no [scene] table and nothing to touch: " in err
    # Either is enough: a named scene with nothing in it (the robot alone), or a bare wall.
    (tmp_path / "named.toml").write_text('[scene]\nname = "bare"\n')
    assert load_scene(tmp_path / "named.toml").name == "bare"
    (tmp_path / "wall.toml").write_text(WALL[WALL.index("[[walls]]") :])
    assert len(load_scene(tmp_path / "wall.toml").walls) == 1


# ----- 6. a mistyped command --------------------------------------------------------------------
@pytest.mark.parametrize(
    ("word", "command"), [("bnech", "bench"), ("rnu", "run"), ("dmeo", "demo")]
)
def test_a_mistyped_command_is_named(word, command, capsys) -> None:
    err = _refused([word], capsys)
    assert err == f"hapticloud: error: unknown command {word!r} (did you mean {command!r}?)"


def test_a_file_named_like_a_command_still_goes_to_the_app(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bnech").write_text("")
    args = cli.build_parser().parse_args(cli.route(["bnech"]))
    assert args.command == "app" and args.scene == "bnech"


# ----- 7. --compare-paper needs --sweep, and says so --------------------------------------------
def test_compare_paper_alone_is_refused_as_its_help_says(wall: str, capsys, no_runs) -> None:
    err = _refused(["run", wall, "--compare-paper"], capsys)
    assert "--compare-paper: needs --sweep" in err and "--sweep KEY=VALUE" in err
    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "only with --sweep" in help_text
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    assert "`--compare-paper` needs `--sweep`" in readme


@pytest.mark.parametrize(
    ("name", "content", "needle"),
    [
        ("noise.toml", bytes(range(128, 256)) * 8, "not text"),
        ("session.mcap", b"\x89MCAP0\r\n" + bytes(range(128, 256)), "a recording (.mcap)"),
        ("cut.toml", b"[scene\nname = ", "not valid TOML"),
    ],
)
@pytest.mark.parametrize("command", ["app", "run"])
def test_a_file_that_is_not_a_scene_is_one_line(
    tmp_path: Path, capsys, name: str, content: bytes, needle: str, command: str
) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    if command == "app" and name.endswith(".mcap"):
        needle = "truncated before its first chunk"  # app opens recordings: the reader says why
    err = _refused(
        [command, str(path), *(["--exit-after", "1"] if command == "app" else [])], capsys
    )
    assert str(path) in err and needle in err
