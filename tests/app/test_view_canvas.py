"""The 3D view's canvas: VTK renders off screen and the paint draws the frame; the mouse turns
and zooms the camera; a released canvas paints nothing of VTK and does not fail."""

from __future__ import annotations

import numpy as np
import pytest
from hapticloud.app.scene_view import SceneView
from hapticloud.hardware.live.scenes import SimSettings, scene_geometry
from PyQt6 import QtCore


@pytest.fixture
def view(qtbot) -> SceneView:
    view = SceneView(render_scale=0.75)
    qtbot.addWidget(view, before_close_func=lambda v: v.close_view())
    view.resize(640, 400)
    view.set_geometry(scene_geometry(SimSettings(decimation=2)))
    view.show()
    qtbot.waitExposed(view)
    return view


def _paints(view: SceneView) -> list[tuple[float, float]]:
    paints: list[tuple[float, float]] = []
    view.canvas.on_paint.append(lambda a, b: paints.append((a, b)))
    return paints


def _camera(view: SceneView) -> tuple[np.ndarray, np.ndarray]:
    cam = view.plotter.renderer.GetActiveCamera()
    return np.array(cam.GetPosition()), np.array(cam.GetFocalPoint())


def test_a_grab_of_the_canvas_is_the_frame_vtk_rendered(view, qtbot) -> None:
    from hapticloud.app.screenshot import qimage_to_array

    grabbed = qimage_to_array(view.canvas.grab().toImage()).astype(int)
    rendered = view.image().astype(int)
    assert grabbed.shape == rendered.shape
    assert grabbed.std() > 5  # the bodies, not a blank widget
    # The same frame, stretched the same way (the paint's filter and the image's may round apart).
    assert np.median(np.abs(grabbed - rendered)) <= 2


def test_dragging_turns_the_camera_and_the_wheel_zooms_in(view, qtbot) -> None:
    paints = _paints(view)
    position, focus = _camera(view)
    centre = view.canvas.rect().center()
    qtbot.mousePress(view.canvas, QtCore.Qt.MouseButton.LeftButton, pos=centre)
    qtbot.mouseMove(view.canvas, centre + QtCore.QPoint(80, 0))
    qtbot.mouseRelease(
        view.canvas, QtCore.Qt.MouseButton.LeftButton, pos=centre + QtCore.QPoint(80, 0)
    )
    qtbot.waitUntil(lambda: len(paints) > 0)
    turned, turned_focus = _camera(view)
    assert np.allclose(turned_focus, focus)  # a turn about the focal point
    assert np.linalg.norm(turned - position) > 1e-3
    distance = np.linalg.norm(turned - turned_focus)
    assert distance == pytest.approx(np.linalg.norm(position - focus), rel=1e-6)

    before = len(paints)
    wheel = QtCore.QPointF(centre)
    event = _wheel_event(wheel, view.canvas.mapToGlobal(wheel), 120)
    view.canvas.wheelEvent(event)
    qtbot.waitUntil(lambda: len(paints) > before)
    zoomed, zoomed_focus = _camera(view)
    assert np.linalg.norm(zoomed - zoomed_focus) < 0.95 * distance


def _wheel_event(pos: QtCore.QPointF, global_pos: QtCore.QPointF, delta: int):
    from PyQt6 import QtGui

    return QtGui.QWheelEvent(
        pos,
        global_pos,
        QtCore.QPoint(0, 0),
        QtCore.QPoint(0, delta),
        QtCore.Qt.MouseButton.NoButton,
        QtCore.Qt.KeyboardModifier.NoModifier,
        QtCore.Qt.ScrollPhase.NoScrollPhase,
        False,
    )


def test_a_released_canvas_paints_without_vtk(view, qtbot) -> None:
    view.close_view()
    paints = _paints(view)
    view.request_render()
    qtbot.waitUntil(lambda: len(paints) > 0)
    assert view.plotter.ren_win is None
    frame = view.canvas.frame()
    assert frame.shape[2] == 3 and (frame == 255).all()
    qtbot.mousePress(view.canvas, QtCore.Qt.MouseButton.LeftButton)  # ignored, no error
