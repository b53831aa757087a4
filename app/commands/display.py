"""Where a command line's window shows: the desktop's display, or a virtual one (``Xvfb``).

VTK needs an X (or Wayland) display for the Qt OpenGL widget; Qt's ``offscreen`` platform has no
OpenGL. So a command that renders without a display starts an ``Xvfb`` server for its duration
(:func:`virtual_display`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

from hapticloud.core.errors import ConfigError, HapticloudError


class DisplayError(HapticloudError):
    """No display to render on and none could be started."""


def has_display() -> bool:
    """True when Qt can open windows with OpenGL here (X11 or Wayland)."""
    if os.environ.get("QT_QPA_PLATFORM", "").startswith(("offscreen", "minimal")):
        return False
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


@contextlib.contextmanager
def virtual_display(size: str = "1920x1080x24") -> Iterator[str]:
    """Run an ``Xvfb`` server for the duration; yields its ``DISPLAY`` (also set in os.environ).

    Raises :class:`DisplayError` when ``Xvfb`` is not installed or does not start.
    """
    exe = shutil.which("Xvfb")
    if exe is None:
        raise DisplayError("no display and no Xvfb to start one (apt-get install xvfb)")
    read_fd, write_fd = os.pipe()
    proc = subprocess.Popen(
        [exe, "-displayfd", str(write_fd), "-screen", "0", size, "-nolisten", "tcp"],
        pass_fds=(write_fd,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(write_fd)
    try:
        with os.fdopen(read_fd) as pipe:
            number = pipe.readline().strip()  # Xvfb writes it once it accepts connections
        if not number:
            raise DisplayError(f"Xvfb did not start (exit code {proc.poll()})")
        saved = {key: os.environ.get(key) for key in ("DISPLAY", "QT_QPA_PLATFORM")}
        os.environ["DISPLAY"] = f":{number}"
        os.environ["QT_QPA_PLATFORM"] = "xcb"
        try:
            yield f":{number}"
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def any_display() -> contextlib.AbstractContextManager[object]:
    """The desktop's display when there is one, else a virtual one for the duration."""
    if has_display():
        return contextlib.nullcontext()
    return virtual_display()


def window_display(
    screenshot: str | None, exit_after: float | None
) -> tuple[contextlib.AbstractContextManager[object], float | None, Path | None]:
    """Where a window of the command line shows: ``(display, exit_after, shot)``.

    A screenshot without ``--exit-after`` is taken after 3 s; without a display, a virtual one
    is started when the window will close by itself, else a one-line error says why not.
    """
    if screenshot and exit_after is None:
        exit_after = 3.0
    shot = Path(screenshot) if screenshot else None
    display: contextlib.AbstractContextManager[object] = contextlib.nullcontext()
    if not has_display():
        if shot is None and exit_after is None:
            raise ConfigError(
                "no display (DISPLAY/WAYLAND_DISPLAY unset or Qt set to offscreen); "
                "run under a desktop, or with --screenshot PATH to render on a virtual display"
            )
        display = virtual_display()
    return display, exit_after, shot


def desktop_application() -> object:
    """The ``QApplication`` of a window command, named as the desktop entry that
    ``hapticloud install-desktop`` installs (so a desktop groups the window under it) and with
    the shipped icon."""
    import sys

    from hapticloud.assets import asset_path
    from PyQt6 import QtGui, QtWidgets

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])
    app.setApplicationName("hapticloud")
    QtGui.QGuiApplication.setDesktopFileName("hapticloud")
    icon = asset_path("icons", "hapticloud.svg")
    if icon.is_file():
        QtWidgets.QApplication.setWindowIcon(QtGui.QIcon(str(icon)))
    return app
