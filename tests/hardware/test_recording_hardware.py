"""``run --hardware --record``: the perception process records each frame and estimate as sent,
the session the loop's snapshots; replay reproduces the session's estimates; a full disk stops
the recording with an alarm while the session runs to its end."""

from __future__ import annotations

from functools import partial
from pathlib import Path

from hapticloud.core.recording import replay, replay_configs
from hapticloud.hardware.recording import format as fmt
from hapticloud.hardware.recording.reader import Recording
from hapticloud.hardware.session.run import run_session, summary_lines


def test_a_hardware_session_records_and_replays_exactly(tmp_path: Path) -> None:
    path = tmp_path / "hw.mcap"
    rep = run_session("impacts", None, 1.5, record=str(path))
    assert rep["recording"]["error"] == "" and rep["recording"]["dropped"] == 0
    assert any(line.startswith(f"wrote {path}") for line in summary_lines(rep))
    with Recording.open(path) as rec:
        assert rec.finished and rec.info["clock"] == "monotonic"
        assert rec.info["source"] == "run --hardware"
        topics = rec.channels
        assert topics[fmt.CONTROL_TOPIC].messages > 50
        assert topics[fmt.EVENTS_TOPIC].messages >= 1  # at least the session's enable
        states = [m.data["state"] for m in rec.messages([fmt.CONTROL_TOPIC])]
        assert "enabled" in states
        perception, fusion = replay_configs(rec.config_toml())
        recorded = {(e.camera, e.seq): e for e in rec.estimates()}
        result = replay(rec.frames(), recorded, perception, fusion)
    summary = result.summary()
    assert summary["frames"] > 20
    assert summary["identical"] == summary["with_recorded_estimate"] == summary["frames"]


def _faults(rep: dict) -> list:
    return [t for t in rep["session"]["transitions"] if t[2] == "fault"]


def test_a_full_disk_stops_the_recording_not_the_session(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    # The drives stepped in the loop: what is under test is the recorder, and the drives' own
    # process on this shared 2-core machine is what a stall faults (under load, 3 of 4 sessions
    # with it faulted here, a drive's command timeout or a feedback loss; 0 of 8 stepped; a
    # fresh-clone CI run faulted twice in a row with it).
    run = partial(
        run_session,
        "impacts",
        None,
        2.5,
        emulator="stepped",
        record=str(path),
        record_limit_bytes=1_000_000,
    )
    rep = run()
    if not rep["enabled_ticks"] > 1800 and _faults(rep):
        # A stall of the loop itself can still fault it (its feedback watchdog). Once more: a
        # recorder that held the loop up would fault it again.
        print("run again after:", _faults(rep))
        path.unlink(missing_ok=True)
        rep = run()
    assert rep["reached_enabled"] and rep["enabled_ticks"] > 1800, _faults(rep)  # it went on
    assert "No space left on device" in rep["recording"]["error"]
    assert rep["recording"]["alarms"]
    with Recording.open(path) as rec:
        assert not rec.finished and rec.message_count > 0
