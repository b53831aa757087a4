"""A recording survives what a session meets: kill -9 of the whole process tree (the file holds
all but the last flush period, info says unfinished, recover rewrites it indexed), a full disk
(the run goes on, the recorder stops with an alarm, the file stays readable), and bad files or
paths given to the command line (exit 2 and one line)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hapticloud.app.cli import main
from hapticloud.core.errors import RecordingError
from hapticloud.core.recording import RecordConfig
from hapticloud.hardware.recording.reader import Recording
from hapticloud.hardware.recording.recover import recover
from hapticloud.hardware.recording.writer import RecordingWriter

HAPTICLOUD = [sys.executable, "-m", "hapticloud.app.cli"]


def _one_line_refusal(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("hapticloud: error: "), err
    return err


def test_kill_9_of_the_process_tree_keeps_all_but_the_last_flush_period(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    # The text demo paced at 30 Hz, recording through its recorder process, in its own group.
    proc = subprocess.Popen(
        [*HAPTICLOUD, "demo", "--duration", "30", "--record", str(path)],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    last_t = 0.0
    try:
        deadline = time.monotonic() + 60.0
        assert proc.stdout is not None
        for line in proc.stdout:  # the demo prints each frame as it is processed
            fields = line.split()
            if fields and fields[0].replace(".", "", 1).isdigit():
                last_t = float(fields[0])
            if last_t >= 3.0 or time.monotonic() > deadline:
                break
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(10)
    assert last_t >= 3.0
    rec = Recording.open(path)
    try:
        assert not rec.finished
        n = rec.message_count
        # Everything up to one flush period (0.5 s; the issue allows 1 s) before the kill.
        assert rec.end_s >= last_t - RecordConfig().flush_period_s - 0.5
        frames = list(rec.frames())
        assert len(frames) > 100
    finally:
        rec.close()
    assert main(["info", str(path)]) == 0
    out = tmp_path / "recovered.mcap"
    assert main(["recover", str(path), str(out)]) == 0
    with Recording.open(out) as again:
        assert again.finished and again.message_count == n


def test_info_says_a_killed_file_is_unfinished(tmp_path: Path, capsys) -> None:
    src = tmp_path / "whole.mcap"
    assert main(["demo", "--duration", "0.5", "--fast", "--record", str(src)]) == 0
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.7)])
    capsys.readouterr()
    assert main(["info", str(cut)]) == 0
    assert "UNFINISHED" in capsys.readouterr().out
    assert main(["replay", str(cut), "--quiet"]) == 0


def test_a_full_disk_stops_the_recording_not_the_run(tmp_path: Path) -> None:
    from hapticloud.core.scene import load_scene
    from hapticloud.core.studies.run import run_scene
    from hapticloud.hardware.recording.runs import frame_hook, record_ticks, scene_recorder

    scene = load_scene("sliding")
    path = tmp_path / "full.mcap"
    recorder = scene_recorder(str(path), scene, "run", "scene", limit_bytes=800_000)
    record = run_scene(scene, None, 1.5, frame_sink=frame_hook(recorder.sink))
    record_ticks(recorder.sink, record)
    result = recorder.close()
    assert record.n_ticks == 1200  # the run went on to its end
    assert "No space left on device" in result["error"]
    assert result["alarms"] and "recording stopped" in result["alarms"][0]
    with Recording.open(path) as rec:  # readable up to its last whole chunk
        assert not rec.finished and rec.message_count > 0
        assert path.stat().st_size <= 800_000


@pytest.mark.parametrize("command", ["info", "replay"])
def test_bad_recordings_are_one_line_and_exit_2(command, tmp_path: Path, capsys) -> None:
    missing = tmp_path / "missing.mcap"
    assert "no such file" in _one_line_refusal([command, str(missing)], capsys)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert "empty" in _one_line_refusal([command, str(empty)], capsys)
    noise = tmp_path / "noise.mcap"
    noise.write_bytes(os.urandom(5000))
    assert "not an MCAP file" in _one_line_refusal([command, str(noise)], capsys)
    whole = tmp_path / "whole.mcap"
    assert main(["demo", "--duration", "0.2", "--fast", "--record", str(whole)]) == 0
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(whole.read_bytes()[:40])
    assert "truncated" in _one_line_refusal([command, str(truncated)], capsys)
    newer = tmp_path / "newer.mcap"
    RecordingWriter(open(newer, "wb"), {"format_version": "99"}, {}).close()
    err = _one_line_refusal([command, str(newer)], capsys)
    assert "format version 99 is not supported" in err
    assert str(newer) in err


def test_record_to_an_unwritable_path_is_refused_before_the_run(
    tmp_path: Path, capsys, monkeypatch
) -> None:
    from hapticloud.core.studies import run

    def started(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("the run started before --record was checked")

    monkeypatch.setattr(run, "run_scene", started)
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    target = str(blocker / "r.mcap")
    err = _one_line_refusal(["run", "sliding", "--record", target], capsys)
    assert err.startswith(f"hapticloud: error: --record {target}")
    err = _one_line_refusal(["demo", "--record", str(tmp_path)], capsys)
    assert "is a folder" in err
    err = _one_line_refusal(
        ["run", "sliding", "--sweep", "surface.speed_mps=1,2", "--record", "x.mcap"], capsys
    )
    assert "--record" in err


def test_recover_refuses_to_overwrite_its_input(tmp_path: Path) -> None:
    src = tmp_path / "a.mcap"
    RecordingWriter(open(src, "wb"), {}, {}).close()
    with pytest.raises(RecordingError, match="must not be the file"):
        recover(src, src)
