"""The main window on the live demo scene: view not blank, sliders reach the pipeline, invalid
values refused, actors never re-added, Esc/Space stop the source."""

from __future__ import annotations

import numpy as np
import pytest
from hapticloud.app.main_window import MainWindow
from hapticloud.app.param_panel import NumberEditor
from hapticloud.app.scene_view import CAMERA_COLOURS
from hapticloud.app.screenshot import grab_window, qimage_to_array
from hapticloud.hardware.live.contract import SourceState
from hapticloud.hardware.live.scenes import SimSettings
from hapticloud.hardware.live.source import LiveSource
from PyQt6 import QtCore, QtWidgets

FAST = SimSettings(decimation=2)  # the demo scene at 424x240: 4x cheaper to simulate
TIMEOUT_MS = 20_000


def _window(qtbot) -> MainWindow:
    window = MainWindow(lambda cfg: LiveSource(FAST, cfg), title="demo")
    qtbot.addWidget(window, before_close_func=lambda w: w.shutdown())
    window.resize(1280, 800)
    window.show()
    qtbot.waitExposed(window)
    qtbot.waitUntil(
        lambda: (
            window.shown is not None
            and window.shown.seq > 10
            and all(c.estimate.valid for c in window.shown.cameras)
        ),
        timeout=TIMEOUT_MS,
    )
    return window


@pytest.fixture(scope="module")
def live(qapp, request):
    """One live window for the tests that do not stop it (a source takes ~2 s to start)."""
    from pytestqt.qtbot import QtBot

    qtbot = QtBot(request)
    window = _window(qtbot)
    yield window, qtbot
    window.shutdown()
    window.close()


def _colour_pixels(image: np.ndarray, hex_colour: str) -> int:
    """Pixels of ``hex_colour``'s hue, saturated: a cloud seen through the translucent body
    keeps its hue but not its exact RGB."""
    from matplotlib.colors import rgb_to_hsv

    hsv = rgb_to_hsv(image[..., :3] / 255.0)
    ref = rgb_to_hsv(np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)]) / 255.0)
    dh = np.abs(hsv[..., 0] - ref[0])
    dh = np.minimum(dh, 1.0 - dh)
    return int(((dh < 0.04) & (hsv[..., 1] > 0.45) & (hsv[..., 2] > 0.3)).sum())


def test_window_opens_on_the_demo_and_the_view_is_not_blank(live) -> None:
    window, _ = live
    assert window.windowTitle() == "hapticloud — demo"
    image = window.view.image()
    h, w, _ = image.shape
    assert (h, w) == (window.view.canvas.height(), window.view.canvas.width())
    assert image.std() > 20  # not a flat background
    assert len(np.unique(image.reshape(-1, 3) // 8, axis=0)) > 100
    # The cameras' kept clouds are drawn in their colours (they overlap on the same surface).
    per_camera = [_colour_pixels(image, CAMERA_COLOURS[i]) for i in range(2)]
    assert sum(per_camera) > 500 and max(per_camera) > 200, per_camera
    # The grab of the whole window carries the 3D view too (composited from VTK's buffer).
    whole = qimage_to_array(grab_window(window))
    assert _colour_pixels(whole, CAMERA_COLOURS[0]) > 200


def test_frame_updates_never_add_actors(live) -> None:
    window, qtbot = live
    actors = window.view.actor_count()
    curves = window.plots.curve_count()
    names = window.view.actor_names
    seq = window.shown.seq
    shown = window.view.frames_shown
    qtbot.waitUntil(lambda: window.view.frames_shown >= shown + 15, timeout=TIMEOUT_MS)
    assert window.shown.seq > seq
    assert window.view.actor_count() == actors
    assert window.view.actor_names == names
    assert window.plots.curve_count() == curves
    # Switching colour mode and layers edits the same actors too.
    window.controls.color_mode.setCurrentText("stage")
    window.controls.layer_actions["bodies"].setChecked(False)
    qtbot.waitUntil(lambda: window.view.frames_shown >= shown + 20, timeout=TIMEOUT_MS)
    assert window.view.actor_count() == actors
    window.controls.color_mode.setCurrentText("camera")
    window.controls.layer_actions["bodies"].setChecked(True)


def test_the_scene_clouds_come_only_while_their_layer_is_shown(live) -> None:
    """Hidden by default: the worker renders none; shown: they arrive; hidden again: they stop."""
    window, qtbot = live
    assert not window.view.layer_visible("context")

    def cloud() -> np.ndarray:
        return window.shown.cameras[0].context

    # Frames keep the last cloud received: an empty one means none was ever rendered.
    assert len(cloud()) == 0
    window.controls.layer_actions["context"].setChecked(True)
    qtbot.waitUntil(lambda: len(cloud()) > 100, timeout=TIMEOUT_MS)
    first = cloud()
    qtbot.waitUntil(lambda: cloud() is not first, timeout=TIMEOUT_MS)  # a new one every 0.2 s
    window.controls.layer_actions["context"].setChecked(False)
    qtbot.wait(300)  # the request reaches the worker; a cloud already sent may still arrive
    kept = cloud()
    shown = window.view.frames_shown
    qtbot.waitUntil(lambda: window.view.frames_shown >= shown + 15, timeout=TIMEOUT_MS)
    assert cloud() is kept  # no new cloud for half a second: the worker renders none


def test_moving_a_slider_changes_the_pipeline_parameter(live) -> None:
    window, qtbot = live
    editor = window.panel.editor("perception.cluster.min_cluster_points")
    assert isinstance(editor, NumberEditor) and editor.slider is not None
    editor.slider.setValue(editor.span.to_slider(45))
    assert window.panel.config.perception.cluster.min_cluster_points == 45
    # The snapshot's config is read back from the worker's pipelines.
    qtbot.waitUntil(
        lambda: window.shown.config.perception.cluster.min_cluster_points == 45,
        timeout=TIMEOUT_MS,
    )
    window.panel.set_value("perception.abstraction.method", "paper")
    qtbot.waitUntil(
        lambda: (
            window.shown.config.perception.abstraction.method == "paper"
            and any(c.estimate.shells for c in window.shown.cameras)
        ),
        timeout=TIMEOUT_MS,
    )
    assert window.view.actor("shell_circles").GetVisibility()


def test_an_invalid_value_is_refused_with_its_message_and_never_applied(live) -> None:
    window, qtbot = live
    before = window.shown.config
    editor = window.panel.editor("perception.crop.workspace_radius_m")
    editor.spin.setValue(0.05)
    message = window.statusBar().currentMessage()
    assert message.startswith("Refused: ")
    assert "must not exceed crop.workspace_radius_m" in message
    assert "must not exceed" in window.panel.error_label.text()
    assert editor.value() == pytest.approx(before.perception.crop.workspace_radius_m)
    seq = window.shown.seq
    qtbot.waitUntil(lambda: window.shown.seq > seq + 4, timeout=TIMEOUT_MS)
    assert window.shown.config.perception.crop == before.perception.crop


def test_the_status_bar_says_whether_the_cameras_agree(live) -> None:
    """The fused quality in words (issue: two cameras that disagree): agree or disagree with the
    distance between the cameras' surfaces, the fusion's note in the tooltip, orange when they
    disagree; a camera that saw two surfaces is counted."""
    import dataclasses

    window, _ = live
    snap = window.shown
    assert snap.fused is not None and snap.fused.valid
    label = window.status.labels["fusion"]
    window.status.show(snap, window.view_fps, force=True)
    assert label.text().startswith(("agree ", "DISAGREE ", "1 camera"))
    alone = dataclasses.replace(snap.fused, cameras=snap.fused.cameras[:1], disagree=False)
    window.status.show(dataclasses.replace(snap, fused=alone), 20.0, force=True)
    assert label.text() == "1 camera"  # nothing to agree with
    fused = dataclasses.replace(
        snap.fused, disagree=True, disagreement_m=0.0042, quality_note="front 4.2 mm farther"
    )
    cam = snap.cameras[0]
    est = dataclasses.replace(cam.estimate, surfaces=2, note="the nearer of two surfaces")
    cameras = (dataclasses.replace(cam, estimate=est), *snap.cameras[1:])
    window.status.show(dataclasses.replace(snap, fused=fused, cameras=cameras), 20.0, force=True)
    assert label.text() == "DISAGREE 4.2 mm, 1 crease"
    assert "b35900" in label.styleSheet()
    assert "front 4.2 mm farther" in label.toolTip()
    assert f"{cam.name}: the nearer of two surfaces" in label.toolTip()


def _restart(window: MainWindow, qtbot) -> None:
    old = window.source
    window.restart()
    qtbot.waitUntil(lambda: window.source.state is SourceState.RUNNING, timeout=TIMEOUT_MS)
    # and shown: a test that stops it next waits for the window to show the stop
    qtbot.waitUntil(
        lambda: window.shown is not None and window.shown.state is SourceState.RUNNING,
        timeout=TIMEOUT_MS,
    )
    assert window.source is not old and not window.stopped
    assert old.state is SourceState.STOPPED and not old.alive


# The stop tests come last: they stop the shared window's source and restart it.
@pytest.mark.parametrize("key", [QtCore.Qt.Key.Key_Escape, QtCore.Qt.Key.Key_Space])
def test_escape_and_space_stop_the_source_whatever_has_focus(live, key) -> None:
    window, qtbot = live
    # Focus a check box: Space would toggle it; the stop must win and swallow the key.
    box = window.panel.editor("perception.reconstruction.enabled").box
    box.setFocus()
    checked = box.isChecked()
    qtbot.keyClick(box, key)
    assert window.stopped
    assert box.isChecked() == checked
    assert "STOPPED" in window.stop_label.text()
    qtbot.waitUntil(lambda: window.source.state is SourceState.STOPPED, timeout=5000)
    qtbot.waitUntil(lambda: window.shown.state is SourceState.STOPPED, timeout=5000)
    assert window.status.labels["state"].text().strip() == "STOPPED"
    assert window.view._banner.GetVisibility()
    assert window.restart_action.isEnabled()
    # Restart: a new simulated session with the panel's parameters; the old one stays stopped.
    _restart(window, qtbot)


def test_space_types_in_a_text_field_but_escape_still_stops(live) -> None:
    window, qtbot = live
    line = QtWidgets.QLineEdit(window)
    line.show()
    line.setFocus()
    qtbot.keyClick(line, QtCore.Qt.Key.Key_Space)
    assert not window.stopped and line.text() == " "
    qtbot.keyClick(line, QtCore.Qt.Key.Key_Escape)
    assert window.stopped
    line.deleteLater()
