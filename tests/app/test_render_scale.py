"""The 3D view's render scale: auto under software OpenGL (Xvfb's llvmpipe here) renders 0.75 of
the widget's pixels, stretched over it; point and line sizes follow; the command line sets it."""

from __future__ import annotations

import numpy as np
import pytest
from hapticloud.app import cli
from hapticloud.app.scene_view import SceneView
from hapticloud.app.view_canvas import SOFTWARE_RENDER_SCALE
from hapticloud.hardware.live.scenes import SimSettings, scene_geometry


def _view(qtbot, scale: float | None) -> SceneView:
    view = SceneView(render_scale=scale)
    qtbot.addWidget(view, before_close_func=lambda v: v.close_view())
    view.resize(800, 500)
    view.set_geometry(scene_geometry(SimSettings(decimation=2)))
    view.show()
    qtbot.waitExposed(view)
    qtbot.waitUntil(lambda: view.render_scale is not None, timeout=10_000)
    return view


def test_auto_renders_fewer_pixels_under_software_opengl_and_shows_them_full_size(qtbot) -> None:
    view = _view(qtbot, None)
    assert view.render_scale == SOFTWARE_RENDER_SCALE  # Xvfb: Mesa's llvmpipe
    ratio = view.canvas.devicePixelRatioF()
    w, h = view.canvas.width() * ratio, view.canvas.height() * ratio
    rw_w, rw_h = view.plotter.render_window.GetSize()
    assert (rw_w, rw_h) == (round(w * SOFTWARE_RENDER_SCALE), round(h * SOFTWARE_RENDER_SCALE))
    assert view.image().shape == (round(h), round(w), 3)  # stretched like the paint
    # A 4 px cloud point stays 4 screen px: 3 render px, stretched by 4/3.
    cloud = next(n for n in view.actor_names if n.startswith("cloud:"))
    assert view.actor(cloud).GetProperty().GetPointSize() == pytest.approx(4 * 0.75)


def test_scale_one_renders_every_pixel(qtbot) -> None:
    view = _view(qtbot, 1.0)
    assert view.render_scale == 1.0
    ratio = view.canvas.devicePixelRatioF()
    size = (round(view.canvas.width() * ratio), round(view.canvas.height() * ratio))
    assert tuple(view.plotter.render_window.GetSize()) == size
    cloud = next(n for n in view.actor_names if n.startswith("cloud:"))
    assert view.actor(cloud).GetProperty().GetPointSize() == 4
    image = view.image()
    assert image.shape[:2] == size[::-1] and np.asarray(image).std() > 5


@pytest.mark.parametrize("value", ["0", "1.5", "0.1", "fast"])
def test_a_render_scale_out_of_range_is_refused(value: str, capsys) -> None:
    with pytest.raises(SystemExit) as exit_:  # argparse's own exit, before any window
        cli.main(["app", "--render-scale", value])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("hapticloud app: error: argument --render-scale: ")
