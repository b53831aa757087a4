"""Shared fixtures. GUI tests get a display that can do OpenGL, started here if there is none.

Qt's ``offscreen`` platform has no OpenGL, and the 3D view renders VTK through GLX; so a GUI
test needs an X display. With ``DISPLAY`` set (a desktop, ``xvfb-run``) it is used as is;
without one, the ``gui_display`` fixture starts ``Xvfb`` for the session (CI runs plain
``pytest``). pytest-qt's ``qapp`` depends on ``qapp_args``, which depends on ``gui_display`` here,
so the display exists before the ``QApplication`` is created. At the end of the session the
``QApplication`` is destroyed before the Xvfb it talks to is stopped (Qt aborts the process when
its X server vanishes under it).

``--headless`` is the run of the core and hardware layers without any GUI library
(``packaging/test.sh`` runs it first, CI too): importing Qt, VTK or a Qt widget library then fails
the import at once, and the session fails if one got in some other way.
"""

from __future__ import annotations

import importlib.abc
import os
import shutil
import sys
from collections.abc import Iterator, Sequence

import pytest


def _usable_display() -> bool:
    platform = os.environ.get("QT_QPA_PLATFORM", "")
    if platform.startswith(("offscreen", "minimal")):
        return False
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


@pytest.fixture(scope="session")
def gui_display() -> Iterator[str]:
    """A display for Qt + OpenGL (``DISPLAY`` value); starts Xvfb when there is none."""
    if _usable_display():
        yield os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY", "")
        return
    pytest.importorskip("PyQt6", reason="the app extras are not installed")
    if shutil.which("Xvfb") is None:
        pytest.skip("no display and no Xvfb to start one (apt-get install xvfb)")
    from hapticloud.app.commands.display import virtual_display

    with virtual_display() as display:
        try:
            yield display
        finally:
            _destroy_qapplication()


def _destroy_qapplication() -> None:
    from PyQt6 import QtWidgets, sip

    app = QtWidgets.QApplication.instance()
    if app is None:
        return
    app.closeAllWindows()
    app.processEvents()
    sip.delete(app)
    # A 3D view's off-screen render window holds its own X connection; one a test left open
    # would end the process (XIO) when the Xvfb stops.
    pyvista = sys.modules.get("pyvista")
    if pyvista is not None:
        pyvista.close_all()


@pytest.fixture(scope="session")
def qapp_args(gui_display: str) -> list[str]:
    """pytest-qt's QApplication arguments; depending on ``gui_display`` orders the two."""
    return ["hapticloud-tests"]


#: The GUI libraries a headless run must never import (top-level package names).
GUI_PACKAGES = ("PyQt6", "pyvista", "pyvistaqt", "vtk", "vtkmodules", "pyqtgraph", "superqt")


class _GuiImportBlocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name: str, path: Sequence[str] | None, target: object = None) -> None:
        if name.split(".")[0] in GUI_PACKAGES:
            raise ImportError(f"headless run: {name} may not be imported by core or hardware")
        return None


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--headless",
        action="store_true",
        help="fail on any import of a GUI library (the core + hardware run)",
    )


def pytest_configure(config: pytest.Config) -> None:
    if config.getoption("--headless"):
        loaded = [name for name in GUI_PACKAGES if name in sys.modules]
        if loaded:
            raise pytest.UsageError(f"--headless: already imported: {', '.join(loaded)}")
        sys.meta_path.insert(0, _GuiImportBlocker())


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    if session.config.getoption("--headless"):
        loaded = [name for name in GUI_PACKAGES if name in sys.modules]
        if loaded:
            print(f"\n--headless: GUI libraries were imported: {', '.join(loaded)}")
            session.exitstatus = pytest.ExitCode.TESTS_FAILED
