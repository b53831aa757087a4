"""``hapticloud --version``: the versions of hapticloud and of the libraries deciding its results.

A bug report carries this block, so it says what ran: the point-cloud, linear-algebra, robot and
QP libraries change numbers; python-can, Qt and VTK change what the hardware and the window do.
Versions are read from the installed distributions' metadata (no import, so it stays quick);
only where that metadata is missing (a bundle that left it out) is the module imported.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import platform
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version

from hapticloud.hardware.recording.writer import software_version

NOT_INSTALLED = "not installed"


@dataclass(frozen=True)
class Library:
    """One library the version block names: its label, distribution and import names."""

    label: str
    distribution: str
    module: str


LIBRARIES: tuple[Library, ...] = (
    Library("Open3D", "open3d", "open3d"),
    Library("numpy", "numpy", "numpy"),
    Library("SciPy", "scipy", "scipy"),
    Library("Pinocchio (pin)", "pin", "pinocchio"),
    Library("daqp", "daqp", "daqp"),
    Library("quadprog", "quadprog", "quadprog"),
    Library("python-can", "python-can", "can"),
    Library("PyQt6", "PyQt6", "PyQt6.QtCore"),
    Library("Qt", "PyQt6-Qt6", "PyQt6.QtCore"),
    Library("VTK", "vtk", "vtkmodules"),
    Library("pyvista", "pyvista", "pyvista"),
)


def library_version(library: Library) -> str:
    """The installed version of ``library``, or :data:`NOT_INSTALLED`."""
    try:
        return version(library.distribution)
    except PackageNotFoundError:
        pass
    if importlib.util.find_spec(library.module.split(".")[0]) is None:
        return NOT_INSTALLED
    try:
        module = importlib.import_module(library.module)
    except ImportError:
        return NOT_INSTALLED
    if library.distribution == "PyQt6-Qt6":
        return str(module.QT_VERSION_STR)
    if library.distribution == "PyQt6":
        return str(module.PYQT_VERSION_STR)
    return str(getattr(module, "__version__", "unknown"))


def version_lines(libraries: Sequence[Library] = LIBRARIES) -> list[str]:
    """The ``--version`` block: hapticloud, Python and one line per library."""
    how = "bundle" if getattr(sys, "frozen", False) else sys.prefix
    lines = [
        f"hapticloud {software_version()}",
        f"Python {platform.python_version()} ({platform.system()} {platform.machine()}, {how})",
    ]
    width = max(len(lib.label) for lib in libraries)
    lines += [f"  {lib.label:<{width}}  {library_version(lib)}" for lib in libraries]
    return lines


class VersionAction(argparse.Action):
    """``--version``: prints :func:`version_lines` and exits 0 (as argparse's own does)."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: object) -> None:
        super().__init__(
            option_strings,
            dest,
            nargs=0,
            default=argparse.SUPPRESS,
            help="print the version of hapticloud and of the libraries that decide its results "
            "(Open3D, numpy, Pinocchio, the QP solvers, python-can, Qt, VTK) and exit",
        )

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        print("\n".join(version_lines()))
        parser.exit(0)
