#!/usr/bin/env bash
# Builds the desktop bundle with PyInstaller (docs/packaging.md): dist/hapticloud/, a folder whose
# executable dist/hapticloud/hapticloud is the whole command line and the app, and the same folder
# as dist/hapticloud-VERSION-linux-ARCH.tar.gz. It runs on a machine with no Python environment.
# Needs Python 3.11 and PyPI (or pip's cache); takes a few minutes and ~3 GB of disk in build/.
# Then: bash packaging/smoke_bundle.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON="${PYTHON:-python3.11}"
venv=build/bundle-venv

# A virtual environment of its own with the run-time set only (no test tools), at the lock's
# versions, the ones the suite passes with: PyInstaller takes what it finds there.
[ -x "$venv/bin/python" ] || "$PYTHON" -m venv "$venv"
"$venv/bin/python" -m pip install -q --upgrade pip
"$venv/bin/python" -m pip install -q -c requirements.lock ".[app,hardware,record]" \
  "pyinstaller>=6.10,<7"
# The same version number does not make pip reinstall: the checkout as it is now, always.
# setuptools copies a module into build/lib only when the source is newer than the copy there, so
# a checkout of older files (git checkout, an unpacked archive) would ship stale modules: start
# from an empty build/lib.
rm -rf build/lib build/bdist.*
"$venv/bin/python" -m pip install -q --no-deps --force-reinstall .

rm -rf dist/hapticloud
"$venv/bin/pyinstaller" --noconfirm --clean --log-level WARN \
  --distpath dist --workpath build/pyinstaller packaging/hapticloud.spec

version="$("$venv/bin/python" -c 'from importlib.metadata import version; print(version("hapticloud"))')"
archive="dist/hapticloud-${version}-linux-$(uname -m).tar.gz"
tar -C dist -czf "$archive" hapticloud
echo "bundle: dist/hapticloud ($(du -sh dist/hapticloud | cut -f1)), $archive ($(du -sh "$archive" | cut -f1))"
