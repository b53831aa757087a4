#!/usr/bin/env bash
# The whole suite, by layer: core + hardware first without any GUI library (a GUI import there
# fails the run), then the app and the contracts (GUI tests under Xvfb, started by the tests).
# Extra arguments go to both pytest runs (e.g. -x, -q).
set -euo pipefail
cd "$(dirname "$0")/.."
status=0
.venv/bin/python -m pytest -p no:pytest-qt --headless tests/core tests/hardware "$@" || status=$?
.venv/bin/python -m pytest tests/app tests/contracts "$@" || status=$?
exit "$status"
