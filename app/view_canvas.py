"""The widget that shows a pyvista scene: VTK renders off screen, the paint draws its pixels.

Why not pyvistaqt's ``QOpenGLWidget``: a window with one ``QOpenGLWidget`` in it is composed
through OpenGL as a whole, so every frame of the 3D view also redraws and transfers every pixel
of the window (panels, plots, status bar). Under software OpenGL (llvmpipe, the 2-core machine
this app targets, under Xvfb) that composition is most of a frame and grows with the window.
Measured side by side in a 1440x900 window with the view at 1062x860 and the demo's actors
(``benchmarks/view_window.py``, alternated, two runs each): the ``QOpenGLWidget`` 34.7 and 29.2
frames/s at 43.6 and 53.1 ms of CPU a frame; this canvas 49.1 and 49.3 frames/s at 28.9 and 29.5
ms. Here VTK renders into its own off-screen frame buffer, the paint reads it back (one
``glReadPixels``) and draws it as an image with ``QPainter``: the rest of the window stays in
Qt's raster backing store and only the view's rectangle is flushed to the display.

The render window has ``render_scale`` times the widget's device pixels (``None``: decided at
the first resize, from the OpenGL renderer: :data:`SOFTWARE_RENDER_SCALE` in software, else 1);
the paint stretches it over the widget with a linear filter, and mouse positions scale the same
way. The mouse drives VTK's trackball camera (rotate, pan with the middle button or shift, zoom
with the wheel or the right button); every interaction schedules one paint.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import pyvista as pv
from PyQt6 import QtCore, QtGui, QtWidgets
from vtkmodules.vtkCommonCore import vtkUnsignedCharArray
from vtkmodules.vtkRenderingUI import vtkGenericRenderWindowInteractor

#: The render scale under software OpenGL (``auto``): VTK renders 0.75 x 0.75 of the widget's
#: pixels and the paint stretches them over it. llvmpipe's shading is most of the view's CPU;
#: point sizes and line widths follow the scale (:class:`~hapticloud.app.scene_view.SceneView`)
#: and text the render window's DPI, so only sharpness changes. A GPU renders at full scale.
SOFTWARE_RENDER_SCALE = 0.75
_SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "software rasterizer")

_PRESS = {
    QtCore.Qt.MouseButton.LeftButton: "LeftButtonPressEvent",
    QtCore.Qt.MouseButton.MiddleButton: "MiddleButtonPressEvent",
    QtCore.Qt.MouseButton.RightButton: "RightButtonPressEvent",
}
_RELEASE = {
    QtCore.Qt.MouseButton.LeftButton: "LeftButtonReleaseEvent",
    QtCore.Qt.MouseButton.MiddleButton: "MiddleButtonReleaseEvent",
    QtCore.Qt.MouseButton.RightButton: "RightButtonReleaseEvent",
}


def software_opengl(capabilities: str) -> bool:
    """Whether VTK's capability report names a software OpenGL renderer (Mesa's llvmpipe...).

    >>> software_opengl("OpenGL renderer string:  llvmpipe (LLVM 15.0.6, 256 bits)")
    True
    >>> software_opengl("OpenGL renderer string:  NVIDIA GeForce RTX 3060/PCIe/SSE2")
    False
    """
    for line in capabilities.splitlines():
        if "renderer string" in line.lower():
            return any(name in line.lower() for name in _SOFTWARE_RENDERERS)
    return False


class ViewCanvas(QtWidgets.QWidget):
    """Shows ``plotter`` (a ``pyvista.Plotter(off_screen=True)``) and hands it the mouse.

    ``update()`` schedules one paint, which renders the scene once; Qt coalesces the requests
    made between two turns of the event loop.
    """

    def __init__(
        self, parent: QtWidgets.QWidget | None, plotter: pv.Plotter, scale: float | None
    ) -> None:
        super().__init__(parent)
        self.plotter = plotter
        self.render_scale: float | None = scale
        #: Called with the scale once it is known (``auto`` decides at the first resize).
        self.on_scale: list[Callable[[float], None]] = []
        #: Called after each paint with its start and end (``time.perf_counter``, s).
        self.on_paint: list[Callable[[float, float], None]] = []
        self._pixels = vtkUnsignedCharArray()
        self._interactor: vtkGenericRenderWindowInteractor | None = plotter.iren.interactor
        # The paint renders; an interaction only moves the camera and asks for a paint.
        self._interactor.EnableRenderOff()
        self.setAttribute(QtCore.Qt.WidgetAttribute.WA_OpaquePaintEvent)
        self.setMouseTracking(True)
        self.setSizePolicy(
            QtWidgets.QSizePolicy.Policy.Expanding, QtWidgets.QSizePolicy.Policy.Expanding
        )

    def release(self) -> None:
        """Close the plotter's render window and let go of it (before the display goes: an
        off-screen render window holds its own X connection until it is destroyed)."""
        self._interactor = None
        self._pixels = vtkUnsignedCharArray()
        self.plotter.close()

    # ----- size -------------------------------------------------------------------------------
    def _ratio(self) -> float:
        return self.devicePixelRatioF() * (self.render_scale or 1.0)

    def render_size(self) -> tuple[int, int]:
        """The render window's size for the widget's present size (device pixels x scale)."""
        ratio = self._ratio()
        return max(1, round(self.width() * ratio)), max(1, round(self.height() * ratio))

    def resizeEvent(self, event: QtGui.QResizeEvent) -> None:  # noqa: N802
        if self.render_scale is None:
            self.render_scale = self._decide_scale()
            for callback in self.on_scale:
                callback(self.render_scale)
        if self._interactor is not None:
            w, h = self.render_size()
            self._interactor.UpdateSize(w, h)
            self.plotter.ren_win.SetSize(w, h)
            self.plotter.ren_win.SetDPI(round(72 * self._ratio()))
        super().resizeEvent(event)

    def _decide_scale(self) -> float:
        window = self.plotter.ren_win
        if window is None:
            return 1.0
        window.Render()  # the capabilities are reported once a context exists
        return SOFTWARE_RENDER_SCALE if software_opengl(window.ReportCapabilities()) else 1.0

    # ----- paint --------------------------------------------------------------------------------
    def _render(self) -> np.ndarray | None:
        """Render the scene now: its ``(H, W, 3)`` RGB rows as OpenGL stores them (bottom row
        first), a view of the canvas's own buffer (reused frame after frame: no allocation per
        frame), or None without a frame (a render window not yet realised, or released)."""
        window = self.plotter.ren_win
        if window is None:
            return None
        window.Render()
        w, h = window.GetSize()
        window.GetPixelData(0, 0, w - 1, h - 1, 0, self._pixels, 0)
        rgb = np.frombuffer(self._pixels, dtype=np.uint8)
        if rgb.size != w * h * 3:
            return None
        return rgb.reshape(h, w, 3)

    def frame(self) -> np.ndarray:
        """The scene rendered now, ``(H, W, 3)`` uint8 RGB from the top row, at the render
        window's size (a copy)."""
        rows = self._render()
        if rows is None:
            w, h = self.render_size()
            return np.full((h, w, 3), 255, np.uint8)
        return rows[::-1].copy()

    def paintEvent(self, event: QtGui.QPaintEvent) -> None:  # noqa: N802
        start = time.perf_counter()
        rows = self._render()
        painter = QtGui.QPainter(self)
        if rows is None:
            painter.fillRect(self.rect(), QtGui.QColor("white"))
        else:
            h, w, _ = rows.shape  # the image borrows the buffer for this paint only
            image = QtGui.QImage(rows.data, w, h, 3 * w, QtGui.QImage.Format.Format_RGB888)
            painter.setRenderHint(QtGui.QPainter.RenderHint.SmoothPixmapTransform)
            # OpenGL's rows run upwards: drawn upside down, no flipped copy.
            painter.translate(0.0, float(self.height()))
            painter.scale(1.0, -1.0)
            painter.drawImage(QtCore.QRectF(0.0, 0.0, self.width(), self.height()), image)
        painter.end()
        if self.on_paint:
            end = time.perf_counter()
            for callback in self.on_paint:
                callback(start, end)

    # ----- mouse --------------------------------------------------------------------------------
    def _interactor_at(
        self, event: QtGui.QMouseEvent | QtGui.QWheelEvent
    ) -> vtkGenericRenderWindowInteractor | None:
        """The interactor, told where ``event`` happened (None once released)."""
        interactor = self._interactor
        if interactor is None:
            return None
        ratio = self._ratio()  # VTK's y axis points up; its pixels are the render window's
        position = event.position()
        modifiers = event.modifiers()
        interactor.SetEventInformation(
            round(position.x() * ratio),
            round((self.height() - position.y() - 1) * ratio),
            int(bool(modifiers & QtCore.Qt.KeyboardModifier.ControlModifier)),
            int(bool(modifiers & QtCore.Qt.KeyboardModifier.ShiftModifier)),
            "\0",
            int(event.type() == QtCore.QEvent.Type.MouseButtonDblClick),
            None,
        )
        return interactor

    def _button(self, table: dict[QtCore.Qt.MouseButton, str], event: QtGui.QMouseEvent) -> None:
        name = table.get(event.button())
        interactor = self._interactor_at(event) if name is not None else None
        if interactor is not None:
            getattr(interactor, name)()
            self.update()

    def mousePressEvent(self, event: QtGui.QMouseEvent) -> None:  # noqa: N802
        self._button(_PRESS, event)

    def mouseDoubleClickEvent(self, event: QtGui.QMouseEvent) -> None:  # noqa: N802
        self._button(_PRESS, event)

    def mouseReleaseEvent(self, event: QtGui.QMouseEvent) -> None:  # noqa: N802
        self._button(_RELEASE, event)

    def mouseMoveEvent(self, event: QtGui.QMouseEvent) -> None:  # noqa: N802
        interactor = self._interactor_at(event)
        if interactor is not None:
            interactor.MouseMoveEvent()
            if event.buttons() != QtCore.Qt.MouseButton.NoButton:
                self.update()

    def wheelEvent(self, event: QtGui.QWheelEvent) -> None:  # noqa: N802
        interactor = self._interactor_at(event)
        if interactor is not None:
            if event.angleDelta().y() >= 0:
                interactor.MouseWheelForwardEvent()
            else:
                interactor.MouseWheelBackwardEvent()
            self.update()
