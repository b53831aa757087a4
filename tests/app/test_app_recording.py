"""The app on a recording: the window with its timeline, seeking shows the frame, keys, re-run,
bad files, and the live window's Record button.

A synthetic recording (a wall, a HIP going to it and back, known holds, stops and a fault) is
written at test time (:mod:`hapticloud.hardware.recording.synth`).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
from hapticloud.app import cli
from hapticloud.app.recording_source import RecordingSource, is_recording
from hapticloud.app.scene_view import CAMERA_COLOURS
from hapticloud.core.scene import load_scene
from hapticloud.hardware.recording.synth import R_HIP_M, gap_m, synthesize
from PyQt6 import QtCore, QtWidgets

TIMEOUT_MS = 20_000


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    return synthesize(tmp_path_factory.mktemp("rec") / "wall.mcap", 3.0)


@pytest.fixture
def window(qtbot, synth: Path):
    from hapticloud.app.recording_window import RecordingWindow

    win = RecordingWindow(RecordingSource.open(synth))
    qtbot.addWidget(win, before_close_func=lambda w: w.shutdown())
    win.resize(1280, 800)
    win.show()
    qtbot.waitExposed(win)
    qtbot.waitUntil(lambda: win.shown is not None, timeout=TIMEOUT_MS)
    qtbot.waitUntil(lambda: win.source.player.timeline.complete, timeout=TIMEOUT_MS)
    return win


def _colour_pixels(image: np.ndarray, hex_colour: str) -> int:
    from matplotlib.colors import rgb_to_hsv

    hsv = rgb_to_hsv(image[..., :3] / 255.0)
    ref = rgb_to_hsv(np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)]) / 255.0)
    dh = np.abs(hsv[..., 0] - ref[0])
    dh = np.minimum(dh, 1.0 - dh)
    return int(((dh < 0.04) & (hsv[..., 1] > 0.45) & (hsv[..., 2] > 0.3)).sum())


def _shown_at(win, t: float) -> bool:
    return win.shown is not None and math.isclose(win.shown.t, t, abs_tol=1e-9)


def test_the_window_shows_the_timeline_under_the_3d_view(window) -> None:
    view, timeline = window.view, window.timeline
    assert timeline.isVisible() and timeline.strip.isVisible()
    view_box = view.geometry()
    assert timeline.geometry().top() >= view_box.bottom()
    assert abs(timeline.width() - view.width()) < 20
    assert window.findChild(QtWidgets.QDockWidget, "Recording") is not None
    # the strip draws the marks of the recording: hold, stop, fault, contacts
    kinds = {m.kind for m in window.source.player.timeline.marks}
    assert kinds == {"hold", "stop", "fault", "contact"}
    assert window.recording_panel.marks.count() == len(window.source.player.timeline.marks)
    strip = timeline.strip.grab().toImage()
    from hapticloud.app.screenshot import qimage_to_array
    from hapticloud.app.timeline import MARK_COLOURS

    pixels = qimage_to_array(strip)
    for kind in ("hold", "stop", "fault", "contact"):
        assert _colour_pixels(pixels, MARK_COLOURS[kind]) > 10, kind


def test_a_click_on_the_strip_seeks_and_the_view_shows_that_frame(window, qtbot) -> None:
    strip = window.timeline.strip
    x = round(strip.x_of(1.5))
    qtbot.mouseClick(strip, QtCore.Qt.MouseButton.LeftButton, pos=QtCore.QPoint(x, 20))
    target = strip.t_of(x)
    assert abs(target - 1.5) < 0.02
    started = time.monotonic()
    qtbot.waitUntil(lambda: _shown_at(window, target), timeout=TIMEOUT_MS)
    elapsed = time.monotonic() - started
    snap = window.shown
    # every camera shows its newest frame at or before the cursor, with its crop and estimate
    assert len(snap.cameras) == 2
    for cam in snap.cameras:
        assert cam.estimate.points is not None and len(cam.estimate.points) > 100
        assert cam.estimate.valid and target - cam.estimate.t < 1 / 30 + 1e-9
    assert snap.fused is not None and snap.fused.valid
    np.testing.assert_allclose(snap.hip[0], R_HIP_M + gap_m(snap.t, 2.0), atol=0.002)
    image = window.view.image()
    assert sum(_colour_pixels(image, c) for c in CAMERA_COLOURS[:2]) > 300
    # the plots got the 10 s before the cursor
    assert len(snap.history.frames) > 60 and len(snap.history.ticks) > 100
    assert elapsed < 5.0  # generous here; docs/benchmarks.md has the measured figure


def test_keys_step_and_play(window, qtbot) -> None:
    player = window.source.player
    player.seek(1.0)
    qtbot.waitUntil(lambda: _shown_at(window, 1.0), timeout=TIMEOUT_MS)
    window.activateWindow()
    qtbot.waitUntil(window.isActiveWindow, timeout=5000)
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Right)
    assert player.position == pytest.approx(1.1)
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Right, QtCore.Qt.KeyboardModifier.ShiftModifier)
    assert player.position == pytest.approx(2.1)
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Left)
    assert player.position == pytest.approx(2.0)
    qtbot.waitUntil(lambda: _shown_at(window, 2.0), timeout=TIMEOUT_MS)
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Home)
    assert player.position == 0.0
    qtbot.keyClick(window, QtCore.Qt.Key.Key_Space)
    assert player.playing
    qtbot.waitUntil(lambda: window.shown.t > 0.2, timeout=TIMEOUT_MS)
    assert window.timeline.play_button.text().endswith("pause")
    qtbot.keyClick(window, QtCore.Qt.Key.Key_K)
    assert not player.playing
    window.timeline.faster(1)
    assert player.speed == 2.0
    qtbot.keyClick(window, QtCore.Qt.Key.Key_BracketLeft)
    assert player.speed == 1.0
    window.timeline.back_large.click()
    assert not player.playing


def test_rerun_draws_the_new_estimates_beside_the_recorded_ones(window, qtbot) -> None:
    window.source.player.seek(1.5)
    window.recording_panel.rerun_button.click()
    rerun = window.source.player.rerun
    assert rerun is not None
    qtbot.waitUntil(lambda: rerun.finished, timeout=120_000)
    assert rerun.error == "" and rerun.done == 181
    window.poll()
    assert "181 frames" in window.recording_panel.summary.text()
    assert window.timeline.strip.rerun is rerun
    # the strip has a re-run lane per camera now
    assert window.timeline.strip.lane_count() == 4
    qtbot.waitUntil(lambda: "markers:rerun:points" in window.view.actor_names, timeout=5000)
    assert window.view.actor("markers:rerun:points").GetVisibility()


def test_parameter_changes_go_to_the_next_rerun(window) -> None:
    panel = window.panel
    assert panel.table_read_only("haptics") and not panel.table_read_only("perception")
    config = panel.config.replace_path("perception.voxel.voxel_size_m", 0.006)
    window._apply_config(config)
    assert window.source.requested_config.perception.voxel.voxel_size_m == 0.006


def test_the_window_s_source_is_a_snapshot_source_for_the_main_window(qtbot, synth) -> None:
    from hapticloud.app.main_window import MainWindow

    source = RecordingSource.open(synth)
    win = MainWindow(lambda cfg: source, title="recording")
    qtbot.addWidget(win, before_close_func=lambda w: w.shutdown())
    win.show()
    qtbot.waitUntil(lambda: win.shown is not None, timeout=TIMEOUT_MS)
    assert len(win.shown.cameras) == 2 and not win.stopped


def test_opening_a_bad_file_inside_the_app_is_a_dialog(qtbot, tmp_path: Path) -> None:
    from hapticloud.app.recording_window import open_recording_window

    bad = tmp_path / "junk.mcap"
    bad.write_bytes(b"\x00" * 100)
    parent = QtWidgets.QWidget()
    qtbot.addWidget(parent)
    assert open_recording_window(bad, parent) is None
    box = parent.findChild(QtWidgets.QMessageBox, "recording-error")
    assert box is not None and box.isVisible()
    assert "junk.mcap: not an MCAP file" in box.text()
    box.close()


def test_recordings_are_told_by_name_or_magic(tmp_path: Path, synth: Path) -> None:
    renamed = tmp_path / "session.bin"
    renamed.write_bytes(synth.read_bytes())
    assert is_recording(synth) and is_recording(renamed)
    assert is_recording(tmp_path / "missing.mcap")
    assert not is_recording("demo") and not is_recording(tmp_path / "missing")


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (None, "no such file"),
        (b"", "empty file"),
        (b"\x89PNG random bytes", "not an MCAP file"),
    ],
)
def test_app_on_a_bad_recording_is_one_line_and_exit_2(
    tmp_path: Path, capsys, content: bytes | None, reason: str
) -> None:
    path = tmp_path / "bad.mcap"
    if content is not None:
        path.write_bytes(content)
    assert cli.main(["app", str(path), "--screenshot", str(tmp_path / "s.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert reason in err and len(err.splitlines()) == 1
    assert not (tmp_path / "s.png").exists()


def test_app_refuses_to_record_a_recording(synth: Path, capsys) -> None:
    assert cli.main(["app", str(synth), "--record", "x.mcap"]) == 2
    assert "is a recording" in capsys.readouterr().err


def test_record_button_records_what_the_live_window_shows(qtbot, tmp_path: Path) -> None:
    from hapticloud.app.main_window import MainWindow
    from hapticloud.app.record_controls import install_record_controls
    from hapticloud.hardware.live.scenes import SimSettings
    from hapticloud.hardware.live.source import LiveSource
    from hapticloud.hardware.recording.reader import Recording

    win = MainWindow(lambda cfg: LiveSource(SimSettings(decimation=2), cfg), title="demo")
    qtbot.addWidget(win, before_close_func=lambda w: w.shutdown())
    win.show()
    controls = install_record_controls(win, folder=tmp_path)
    assert controls.button.text().endswith("Record")
    qtbot.waitUntil(lambda: win.shown is not None and win.shown.seq > 3, timeout=TIMEOUT_MS)
    controls.button.click()
    rec = controls.recording
    assert rec is not None
    qtbot.waitUntil(lambda: rec.state == "recording", timeout=TIMEOUT_MS)
    qtbot.waitUntil(lambda: rec.status().messages > 40, timeout=TIMEOUT_MS)
    qtbot.waitUntil(lambda: "MB" in controls.label.text(), timeout=2000)
    assert controls.label.text().startswith("REC hapticloud-")
    assert controls.button.text().endswith("Stop recording")
    config = win.panel.config.replace_path("perception.voxel.voxel_size_m", 0.005)
    win.panel.config_changed.emit(config)
    controls.button.click()
    qtbot.waitUntil(lambda: rec.state == "done", timeout=60_000)
    assert controls.button.text().endswith("Record")
    with Recording.open(rec.path) as recording:
        counts = {t: c.messages for t, c in recording.channels.items()}
        names = sorted(c.name for c in load_scene("demo").cameras)
        assert recording.info["source"] == "app" and sorted(recording.cameras) == names
        assert all(counts[f"/camera/{name}/depth"] > 5 for name in names)
        assert all(counts[f"/perception/{name}/estimate"] > 5 for name in names)
        events = [m.data.message for m in recording.messages(["/events"])]
        assert any("voxel_size_m" in e for e in events)
        frames = list(recording.frames(["front"]))
        assert all(f.roi[1] > f.roi[0] for f in frames)
