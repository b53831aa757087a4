"""Imports point one way: app -> hardware -> core. core never imports Qt, pyvista or python-can;
hardware never imports Qt; app runs no process or thread of its own outside its command layer
(``app/commands/``, ``app/cli.py``): those live in hardware/."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
GUI = {
    "PyQt6",
    "PyQt5",
    "PySide6",
    "PySide2",
    "pyvista",
    "pyvistaqt",
    "vtk",
    "vtkmodules",
    "superqt",
    "pyqtgraph",
    "qtpy",
    "matplotlib.backends.backend_qtagg",
}
BUS = {"can", "cantools", "canopen"}
CONCURRENCY = {"threading", "multiprocessing", "subprocess", "concurrent"}
FORBIDDEN = {
    "core": GUI | BUS | {"hapticloud.hardware", "hapticloud.app", "threading", "multiprocessing"},
    "hardware": GUI | {"hapticloud.app"},
    "app": CONCURRENCY,
}
#: What may do what the rest of its layer may not: the command line starts virtual displays
#: and runs the hardware layer's processes from its handlers.
EXEMPT = {"app": ("app/commands/", "app/cli.py")}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    package = "hapticloud." + ".".join(path.relative_to(ROOT).parent.parts)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                names.add(".".join([*base, node.module] if node.module else base))
            elif node.module:
                names.add(node.module)
    return names


def _violations(layer: str) -> list[str]:
    bad = []
    for path in sorted((ROOT / layer).rglob("*.py")):
        if path.relative_to(ROOT).as_posix().startswith(EXEMPT.get(layer, ())):
            continue
        for name in _imports(path):
            for forbidden in FORBIDDEN[layer]:
                if name == forbidden or name.startswith(forbidden + "."):
                    bad.append(f"{path.relative_to(ROOT)} imports {name}")
    return bad


@pytest.mark.parametrize("layer", ["core", "hardware", "app"])
def test_static_imports_point_one_way(layer: str) -> None:
    assert _violations(layer) == []


def test_importing_all_of_core_loads_no_gui_or_bus_module() -> None:
    code = (
        "import importlib, pkgutil, sys\n"
        "import hapticloud.core as core\n"
        "for m in pkgutil.walk_packages(core.__path__, 'hapticloud.core.'):\n"
        "    importlib.import_module(m.name)\n"
        f"bad = sorted(n for n in sys.modules if n.split('.')[0] in {sorted(GUI | BUS)!r})\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""
