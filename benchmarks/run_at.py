"""Run a ``hapticloud`` command on another checkout, with this environment's packages.

For figures side by side with a parent commit on the same machine, the same day::

    git worktree add /tmp/base HEAD~1
    .venv/bin/python benchmarks/run_at.py /tmp/base bench perception --frames 60
    .venv/bin/python benchmarks/run_at.py . bench perception --frames 60

The editable install maps ``hapticloud.core`` and its siblings to this repository's folders; the
mapping is pointed at ``CHECKOUT`` before anything of ``hapticloud`` is imported. Worker
processes (``bench safety`` without ``--workers 1``) would import this repository again: run them
with ``--workers 1``.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path


def _point_the_install_at(checkout: Path) -> None:
    finders = [
        m.name for m in pkgutil.iter_modules() if m.name.startswith("__editable___hapticloud")
    ]
    if not finders:
        raise SystemExit("run_at: hapticloud is not installed in editable mode here")
    finder = importlib.import_module(finders[0])
    for name, path in list(finder.MAPPING.items()):
        finder.MAPPING[name] = str(checkout / Path(path).name)


def main() -> int:
    if len(sys.argv) < 3:
        raise SystemExit("usage: run_at.py CHECKOUT HAPTICLOUD-ARGS...")
    checkout = Path(sys.argv.pop(1)).resolve()
    if not (checkout / "core" / "__init__.py").is_file():
        raise SystemExit(f"run_at: {checkout} is not a hapticloud checkout (no core/__init__.py)")
    _point_the_install_at(checkout)
    import hapticloud.core

    assert Path(hapticloud.core.__file__).is_relative_to(checkout), hapticloud.core.__file__
    from hapticloud.app.cli import main as cli

    return int(cli() or 0)


if __name__ == "__main__":
    sys.exit(main())
