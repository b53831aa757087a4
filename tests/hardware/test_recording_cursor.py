"""The recording's cursor, timeline, re-run and live recorder (hardware layer, no Qt).

A synthetic recording (:mod:`hapticloud.hardware.recording.synth`: a wall, a HIP going to it and
back, known holds, stops and a fault) is written at test time in a fraction of a second.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
from hapticloud.core.errors import RecordingError
from hapticloud.hardware.recording.cursor import CursorReader, RecordingPlayer, read_layout
from hapticloud.hardware.recording.reader import Recording
from hapticloud.hardware.recording.synth import R_HIP_M, SynthTimes, gap_m, synthesize
from hapticloud.hardware.recording.timeline import (
    TimelineScan,
    intervals,
    merge_marks,
    timeline_marks,
)

PERIOD = 2.0
FRAME_DT = 1.0 / 30.0


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    return synthesize(tmp_path_factory.mktemp("rec") / "wall.mcap", 3.0, period_s=PERIOD)


@pytest.fixture(scope="module")
def stopped_camera(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "stops.mcap"
    return synthesize(path, 3.0, period_s=PERIOD, camera_stops_s={"side": 0.8})


def _wait(pred, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            raise AssertionError("timed out")
        time.sleep(0.005)


def test_layout_reads_cameras_radius_shapes_and_parameters(synth: Path) -> None:
    with Recording.open(synth) as rec:
        layout = read_layout(rec)
    assert [c.name for c in layout.cameras] == ["front", "side"]
    np.testing.assert_allclose(layout.cameras[0].origin, (0.7, 0.15, 0.35))
    assert layout.cameras[0].axis[0] < -0.9  # looks at the wall (-x)
    assert layout.r_hip_m == pytest.approx(R_HIP_M)
    assert layout.shapes[0] == "sphere" and set(layout.shapes[1:]) == {"capsule"}
    assert layout.perception.crop.workspace_radius_m > 0 and layout.note == ""


@pytest.mark.parametrize("t", [0.05, 0.61, 1.5, 2.99, 3.0])
def test_every_channel_shows_its_newest_message_at_or_before_the_cursor(
    synth: Path, t: float
) -> None:
    with Recording.open(synth) as rec:
        reader = CursorReader(rec, read_layout(rec))
        view = reader.at(t)
    assert view.t == pytest.approx(t)
    for cam in view.cameras:
        assert cam.log_time_s <= t + 1e-9 and t - cam.log_time_s < FRAME_DT + 1e-9, cam.name
        assert cam.frame is not None and cam.frame.camera == cam.name
        # the frame's crop: points on the wall x = 0, within the workspace of its HIP
        assert len(cam.cropped) > 100 and np.abs(cam.cropped[:, 0]).max() < 1e-4
        assert len(cam.context) > 0
        # the estimate recorded for that frame: the HIP's projection on the wall
        est = cam.estimate
        assert est is not None and est.seq == cam.frame.seq
        np.testing.assert_allclose(est.centroid, (0.0, 0.0, 0.3), atol=1e-12)
    control = view.control
    assert control is not None and control["log_time_s"] <= t + 1e-9
    assert t - control["log_time_s"] < 0.01 + 1e-9
    np.testing.assert_allclose(view.hip, (R_HIP_M + gap_m(control["t"], PERIOD), 0.0, 0.3))
    assert view.fused_source == "recorded"
    assert view.fused_d_proj_m == pytest.approx(gap_m(control["t"], PERIOD))


def test_a_camera_before_its_first_frame_is_empty(synth: Path) -> None:
    with Recording.open(synth) as rec:
        view = CursorReader(rec, read_layout(rec)).at(0.0)
    front, side = view.cameras
    assert front.frame is not None and front.log_time_s == 0.0
    assert side.frame is None and side.estimate is None and len(side.cropped) == 0


def test_a_camera_that_stopped_shows_its_last_frame_not_a_blank(stopped_camera: Path) -> None:
    """No blank view after a seek: the look-back widens until the newest frame is found."""
    with Recording.open(stopped_camera) as rec:
        reader = CursorReader(rec, read_layout(rec))
        view = reader.at(2.9)
    side = {c.name: c for c in view.cameras}["side"]
    assert side.frame is not None and 0.75 < side.log_time_s <= 0.8
    assert len(side.cropped) > 100


def test_timeline_marks_faults_holds_stops_and_contacts(synth: Path) -> None:
    published = []
    with Recording.open(synth) as rec:
        data = TimelineScan(rec, R_HIP_M).run(published.append, every_messages=100)
    assert data.complete and data.error == "" and published[-1] is data
    assert len(published) > 2 and not published[0].complete  # it publishes as it goes
    assert [len(lane.t) for lane in data.cameras] == [91, 90]
    assert len(data.control.t) == 301 and len(data.events) == 6
    times = SynthTimes()
    by_kind: dict[str, list] = {}
    for m in data.marks:
        by_kind.setdefault(m.kind, []).append((m.t0, m.t1))
    assert by_kind["hold"] == [pytest.approx(times.hold, abs=1e-9)]
    assert by_kind["stop"] == [pytest.approx(times.stop, abs=1e-9)]
    assert pytest.approx(times.fault, abs=1e-9) in by_kind["fault"]
    assert (times.fault[0], times.fault[0]) in by_kind["fault"]  # the event, a point
    # contacts: the true margin under 5 mm, around each minimum of the gap (t = 1, 3)
    contacts = by_kind["contact"]
    assert len(contacts) == 2
    for (t0, t1), centre in zip(contacts, (1.0, 3.0), strict=True):
        assert t0 < centre <= t1 + 1e-9 and gap_m(t0, PERIOD) < 0.005
    # invalid estimates while the session was stopped for want of a surface
    lane = data.cameras[0]
    blind = (lane.t >= times.stop[0]) & (lane.t < times.stop[1])
    assert not lane.valid[blind].any() and lane.valid[~blind].all()
    assert np.isnan(lane.d_proj_mm[blind]).all()
    np.testing.assert_allclose(
        lane.d_proj_mm[~blind], [1e3 * gap_m(t, PERIOD) for t in lane.t[~blind]], atol=1e-9
    )


def test_intervals_and_merging() -> None:
    t = np.arange(10.0)
    on = np.array([0, 1, 1, 0, 0, 1, 0, 0, 0, 1], bool)
    assert intervals(t, on) == [(1.0, 3.0), (5.0, 6.0), (9.0, 9.0)]
    assert intervals(t, on, end_s=12.0) == [(1.0, 3.0), (5.0, 6.0), (9.0, 12.0)]
    from hapticloud.hardware.recording.timeline import Mark

    marks = [Mark("hold", 0, 1), Mark("hold", 1.5, 2), Mark("hold", 5, 6), Mark("stop", 1, 1)]
    assert [(m.kind, m.t0, m.t1) for m in merge_marks(marks, 1.0)] == [
        ("hold", 0, 2),
        ("stop", 1, 1),
        ("hold", 5, 6),
    ]


def test_fault_events_are_marked(synth: Path) -> None:
    from hapticloud.hardware.recording.timeline import Event, empty_timeline

    data = empty_timeline(0.0, 1.0, [])
    import dataclasses

    events = (
        Event(0.1, "info", "reaction", "NONE: all clear"),
        Event(0.2, "warning", "reaction", "DAMPING camera: stale"),
        Event(0.3, "info", "state", "emergency_stop: key"),
        Event(0.4, "info", "state", "ready: reset"),
        Event(0.5, "info", "space", "holding: stale"),
    )
    events += (Event(0.6, "warning", "reaction", "HOLD_SURFACE estimate: 0.05 s old"),)
    marks = timeline_marks(dataclasses.replace(data, events=events))
    assert [(m.t0, m.kind) for m in marks] == [(0.2, "fault"), (0.3, "fault"), (0.6, "hold")]


def test_player_seeks_steps_plays_and_pauses(synth: Path) -> None:
    player = RecordingPlayer(synth)
    try:
        player.start()
        _wait(lambda: player.view is not None and player.timeline.complete)
        player.seek(1.5)
        _wait(lambda: player.view.t == 1.5)
        assert player.view.decode_ms < 1000
        player.step(0.1)
        _wait(lambda: player.view.t == pytest.approx(1.6))
        player.step(-10.0)
        _wait(lambda: player.view.t == 0.0)  # clamped at the start
        player.seek(99.0)
        _wait(lambda: player.view.t == 3.0)
        player.play()  # at the end: plays again from the start
        assert player.playing and player.position < 0.5
        player.set_speed(4.0)
        _wait(lambda: player.view.t > 1.0)
        player.pause()
        held = player.position
        time.sleep(0.1)
        assert not player.playing and player.position == held
        player.play()
        _wait(lambda: not player.playing, timeout=5.0)  # stops at the end
        assert player.position == 3.0
        _wait(lambda: player.view.t == 3.0)
    finally:
        player.close()
    with pytest.raises(Exception, match="speed"):
        player.set_speed(0.0)


def test_an_unfinished_file_plays_what_it_holds(synth: Path, tmp_path: Path) -> None:
    torn = tmp_path / "torn.mcap"
    data = synth.read_bytes()
    torn.write_bytes(data[: len(data) // 2])
    player = RecordingPlayer(torn)
    try:
        assert not player.rec.finished
        player.start()
        _wait(lambda: player.timeline.complete)
        end = player.end_s
        assert 0.5 < end < 3.0
        player.seek(end)
        _wait(lambda: player.view is not None and player.view.t == end)
        assert all(c.frame is not None for c in player.view.cameras)
    finally:
        player.close()


@pytest.mark.parametrize("content", [b"", b"not a recording at all", None])
def test_bad_files_raise_one_line(tmp_path: Path, content: bytes | None) -> None:
    path = tmp_path / "bad.mcap"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(RecordingError) as err:
        RecordingPlayer(path)
    assert len(str(err.value).splitlines()) == 1 and "bad.mcap" in str(err.value)


def test_rerun_streams_one_row_per_frame(synth: Path) -> None:
    player = RecordingPlayer(synth, scan=False)
    try:
        rerun = player.start_rerun(player.layout.perception, player.layout.fusion)
        assert rerun.wait(120.0), rerun.error
        assert rerun.error == "" and rerun.total == 181
        rows = rerun.rows
        assert len(rows.rows) == 181 and rerun.summary["frames"] == 181
        front = rows.camera_rows("front")
        np.testing.assert_allclose(front[:, 0], np.arange(91) / 30.0, atol=1e-9)
        # the recorded estimates ride along: the exact projection of the HIP
        recorded = rows.d_proj_mm(front, R_HIP_M, "rec")
        expected = [1e3 * gap_m(t, PERIOD) for t in front[:, 0]]
        ok = np.isfinite(recorded)
        np.testing.assert_allclose(recorded[ok], np.asarray(expected)[ok], atol=1e-9)
        # the pipeline finds the wall where the HIP is near it
        new = rows.d_proj_mm(front, R_HIP_M, "new")
        near = ok & np.isfinite(new) & (recorded < 60)
        assert near.sum() > 10
        assert np.abs(new[near] - recorded[near]).max() < 3.0
    finally:
        player.close()


def test_rerun_cancel_ends_the_process(synth: Path) -> None:
    player = RecordingPlayer(synth, scan=False)
    try:
        rerun = player.start_rerun(player.layout.perception, player.layout.fusion)
        rerun.cancel()
        assert rerun.finished and rerun.cancelled and not rerun._proc.is_alive()
        assert not rerun.poll()
    finally:
        player.close()


def test_live_recording_writes_what_it_is_fed(synth: Path, tmp_path: Path) -> None:
    """The app's recorder: frames cut elsewhere, control snapshots, events, finished off the
    caller's thread; the file opens and plays."""
    from types import SimpleNamespace

    from hapticloud.core.camera import DepthFrame
    from hapticloud.core.perception import PerceptionConfig
    from hapticloud.core.recording import RecordConfig
    from hapticloud.hardware.recording.live import LiveRecording
    from hapticloud.hardware.recording.recorder import cut_frame

    out = tmp_path / "live.mcap"
    perception = PerceptionConfig()
    from hapticloud.core.fusion import FusionConfig

    live = LiveRecording(out, perception, FusionConfig(), scene="wall")
    assert live.status().state == "starting"
    assert live.wait(30.0) and live.state == "recording", live.status()
    with Recording.open(synth) as rec:
        frames = list(rec.frames(None, 0.0, 0.5))
        ests = {(e.camera, e.seq): e for e in rec.estimates(None, 0.0, 0.5)}
    t0 = time.monotonic()
    for cap in frames:
        frame = DepthFrame(
            cap.frame.t,
            cap.camera,
            cap.frame.depth_m,
            cap.frame.intrinsics,
            cap.frame.pose_world_camera,
        )
        est = ests[(cap.camera, cap.seq)]
        cut = cut_frame(frame, cap.hip, cap.exclude, est, perception.crop, RecordConfig())
        live.put_cut(t0 + cap.log_time_s, cut)
    snap = SimpleNamespace(
        t=t0 + 0.25,
        hip_m=(0.05, 0.0, 0.3),
        q=(0.0,) * 6,
        tau_sent=(0.0,) * 6,
        d_proj_m=0.01,
        fused_valid=True,
        state="enabled",
        reaction="NONE",
        space="known",
        space_reason="",
        tick_us=250.0,
        misses=0,
        events=((t0 + 0.3, "state", "fault: test"),),
    )
    live.control_snapshots([snap], R_HIP_M)
    live.event("info", "config", "parameters changed: x 1 -> 2")
    status = live.status()
    assert status.path == str(out) and status.duration_s >= 0 and "live.mcap" in status.line()
    live.stop()
    assert live.state in ("finishing", "done")
    assert live.wait_done(60.0) and live.state == "done", live.status()
    # depth, its cloud, calibration, capture, estimate per frame; a transform per camera; the
    # control state and its surface; two events
    assert live.result["messages"] == 5 * len(frames) + 2 + 2 + 2
    player = RecordingPlayer(out)
    try:
        assert player.rec.finished and player.rec.info["source"] == "app"
        assert player.rec.info["clock"] == "monotonic"
        assert player.rec.cameras == ["front", "side"]
        player.start()
        _wait(lambda: player.timeline.complete)
        assert any(m.kind == "fault" for m in player.timeline.marks)
        player.seek(t0 + 0.4)
        _wait(lambda: player.view is not None and math.isclose(player.view.t, t0 + 0.4))
        assert all(c.frame is not None and len(c.cropped) > 100 for c in player.view.cameras)
    finally:
        player.close()


def test_a_recording_that_cannot_start_says_why(tmp_path: Path) -> None:
    from hapticloud.core.fusion import FusionConfig
    from hapticloud.core.perception import PerceptionConfig
    from hapticloud.hardware.recording.live import LiveRecording

    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    live = LiveRecording(blocker / "x.mcap", PerceptionConfig(), FusionConfig())
    assert live.wait(30.0)
    assert live.state == "failed" and "x.mcap" in live.status().error
    assert live.sink is None
    live.stop()  # nothing to stop
    assert live.state == "failed"


def test_seek_bench_reports_open_and_seek_figures(synth: Path) -> None:
    from hapticloud.hardware.recording.seek_bench import seek_bench, seek_lines

    said: list[str] = []
    result = seek_bench(synth, seeks=5, say=said.append)
    assert result["finished"] and result["duration_s"] == pytest.approx(3.0)
    assert 0 < result["open_ms"] < 2000 and result["seek_ms"]["n"] == 5
    assert result["seek_ms"]["max"] < 2000 and result["scan_s"] > 0
    lines = seek_lines(result)
    assert any("open (index only" in line for line in lines) and said


def test_indexed_and_streamed_files_show_the_same_messages(synth: Path, tmp_path: Path) -> None:
    """A finished file is read through its message indexes, an unfinished one chunk by chunk:
    the same message either way."""
    torn = tmp_path / "torn.mcap"
    data = synth.read_bytes()
    torn.write_bytes(data[: len(data) * 2 // 3])
    with Recording.open(synth) as full, Recording.open(torn) as part:
        assert full.indexed and not part.indexed
        a, b = CursorReader(full, read_layout(full)), CursorReader(part, read_layout(part))
        # (the torn file lacks what was in its torn last chunk: compare well before its end)
        for t in np.linspace(0.0, part.end_s - 0.6, 9):
            va, vb = a.at(float(t)), b.at(float(t))
            assert [c.log_time_s for c in va.cameras] == [c.log_time_s for c in vb.cameras]
            for ca, cb in zip(va.cameras, vb.cameras, strict=True):
                if ca.frame is not None:
                    np.testing.assert_array_equal(ca.cropped, cb.cropped)
                    assert ca.estimate.seq == cb.estimate.seq
                    np.testing.assert_array_equal(ca.estimate.centroid, cb.estimate.centroid)
            assert va.control == vb.control
