"""Screenshots of the window (3D view included), and running a command line's window.

``QWidget.grab()`` renders the widgets through Qt's raster paint, the 3D view included: its
canvas (:class:`~hapticloud.app.view_canvas.ViewCanvas`) renders VTK off screen and paints the
frame as an image, so the PNG shows what VTK drew.

:func:`run_window` runs a window until it closes or for a set time, then saves its screenshot;
where it shows (a virtual display for a headless run) is :mod:`hapticloud.app.commands.display`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from PyQt6 import QtGui, QtWidgets


def qimage_from_rgb(rgb: NDArray[np.uint8]) -> QtGui.QImage:
    """A QImage owning a copy of ``(H, W, 3)`` uint8 RGB pixels."""
    rgb = np.ascontiguousarray(rgb[..., :3], dtype=np.uint8)
    h, w, _ = rgb.shape
    image = QtGui.QImage(rgb.data, w, h, 3 * w, QtGui.QImage.Format.Format_RGB888)
    return image.copy()  # own the pixels: ``rgb`` is freed when we return


def qimage_to_array(image: QtGui.QImage) -> NDArray[np.uint8]:
    """``(H, W, 3)`` uint8 RGB copy of a QImage."""
    image = image.convertToFormat(QtGui.QImage.Format.Format_RGB888)
    h, w = image.height(), image.width()
    data = np.frombuffer(image.constBits().asstring(image.sizeInBytes()), np.uint8)
    return data.reshape(h, image.bytesPerLine())[:, : 3 * w].reshape(h, w, 3).copy()


def grab_window(window: QtWidgets.QWidget) -> QtGui.QImage:
    """The whole window as an image, the 3D view included (its canvas paints VTK's frame)."""
    QtWidgets.QApplication.processEvents()
    return window.grab().toImage()


def save_window(window: QtWidgets.QWidget, path: Path) -> Path:
    """Write :func:`grab_window` to ``path`` as PNG; raises :class:`OSError` if it cannot."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not grab_window(window).save(str(path), "PNG"):
        raise OSError(f"{path}: could not write the PNG")
    return path


def run_window(
    app: object,
    window: object,
    shot: Path | None,
    exit_after: float | None,
    before_close: object = None,
) -> int:
    """Run the Qt event loop of ``window`` until it closes, or for ``exit_after`` seconds; then
    save ``shot`` (a PNG of the window) and tear Qt down while the display still exists.

    ``before_close`` (a callable) runs first at the timed exit (e.g. writing a report). Returns
    the exit code: 2 if the screenshot could not be written, else 0.
    """
    import sys

    from PyQt6 import QtCore, sip

    result = {"code": 0}

    def finish() -> None:
        if callable(before_close):
            before_close()
        if shot is not None:
            try:
                path = save_window(window, shot)
                print(f"screenshot: {path}", flush=True)
            except OSError as err:
                print(f"hapticloud: error: {err}", file=sys.stderr)
                result["code"] = 2
        window.close()  # type: ignore[attr-defined]
        app.quit()  # type: ignore[attr-defined]

    if exit_after is not None:
        QtCore.QTimer.singleShot(round(1000 * exit_after), finish)
    app.exec()  # type: ignore[attr-defined]
    window.shutdown()  # type: ignore[attr-defined]
    # Destroy Qt's objects now, while the display still exists: a virtual display is stopped
    # right after this returns, and Qt talking to a vanished X server aborts the process.
    window.deleteLater()  # type: ignore[attr-defined]
    app.processEvents()  # type: ignore[attr-defined]
    sip.delete(app)
    return result["code"]
