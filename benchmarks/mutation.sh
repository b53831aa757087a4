#!/usr/bin/env bash
# Mutation testing of the safety code (docs/testing.md):
#
#   bash benchmarks/mutation.sh [MODULE ...] [--jobs N] [--workdir DIR] [--fail-under PCT]
#
# MODULE is a file such as core/haptics/velocity.py; without one, the default set in
# pyproject.toml's [tool.mutmut] only_mutate. Runs mutmut in build/mutation/ (a copy of the
# repository laid out as installed, see benchmarks/mutation.py), one mutant at a time unless
# --jobs or MUTATION_JOBS says otherwise. Exclusions, each with its reason: benchmarks/mutation.toml.
# The last line printed is the summary as one JSON line; exit code 0 when every module scores at
# least --fail-under (90 %), 1 when one does not, 2 when the run could not be made.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/mutmut ]; then
  echo "mutation: .venv/bin/mutmut missing: run 'bash packaging/bootstrap.sh' first" >&2
  exit 2
fi
exec .venv/bin/python benchmarks/mutation.py "$@"
