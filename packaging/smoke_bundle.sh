#!/usr/bin/env bash
# Smoke test of the built bundle (packaging/build_bundle.sh first): --version, the text demo and
# the app's window under Xvfb, each run from an empty folder with no Python environment in sight
# (an emptied environment: no PATH entry to a Python, no PYTHONPATH, no virtual environment).
# Prints each step's wall time. Usage: bash packaging/smoke_bundle.sh [BUNDLE_DIR]
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
bundle="$(cd "${1:-$root/dist/hapticloud}" && pwd)"
exe="$bundle/hapticloud"
[ -x "$exe" ] || { echo "smoke: no bundle at $bundle (run packaging/build_bundle.sh)" >&2; exit 2; }
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
cd "$work"

bare() { env -i HOME="$work" PATH=/usr/bin:/bin LANG=C.UTF-8 "$@"; }
step() {
  local name="$1"; shift
  local t0 t1
  t0=$(date +%s%N)
  if ! "$@" >"$work/$name.out" 2>&1; then
    echo "smoke: FAIL $name" >&2; tail -20 "$work/$name.out" >&2; exit 1
  fi
  t1=$(date +%s%N)
  local ms=$(((t1 - t0) / 1000000))
  printf 'smoke: ok   %-10s %3d.%02d s\n' "$name" $((ms / 1000)) $((ms % 1000 / 10))
}

step version bare "$exe" --version
grep -q "^hapticloud [0-9]" "$work/version.out"
grep -q "(Linux .*, bundle)$" "$work/version.out"  # the bundle's own Python, not an environment's
for lib in Open3D numpy "Pinocchio (pin)" daqp quadprog python-can PyQt6 Qt VTK pyvista; do
  if ! grep -q "^  $lib  *[0-9]" "$work/version.out"; then
    echo "smoke: FAIL --version does not name $lib" >&2; cat "$work/version.out" >&2; exit 1
  fi
done
step version2 bare "$exe" --version  # warm: the files are in the page cache
step demo bare "$exe" demo --duration 1
step run bare "$exe" run impacts --duration 1 --quiet
step record bare "$exe" run impacts --duration 1 --quiet --record "$work/run.mcap"
step info bare "$exe" info "$work/run.mcap"
grep -q "finished (indexed)" "$work/info.out"
step app bare xvfb-run -a "$exe" app --screenshot "$work/app.png" --exit-after 3 \
  --report "$work/app.json"
[ -s "$work/app.png" ] || { echo "smoke: FAIL the app wrote no screenshot" >&2; exit 1; }
# The window's hardware session (control process, emulated drives on a virtual CAN bus) must
# have started: a module the bundle left out shows there as a failed session, not as an error.
if grep -q '"failed"' "$work/app.json"; then
  echo "smoke: FAIL the app's session failed" >&2; cat "$work/app.json" >&2; exit 1
fi
cp "$work/app.png" "$root/dist/smoke-app.png" 2>/dev/null || true
# The desktop entry the bundle installs starts the bundle's executable and validates.
step desktop bare env XDG_DATA_HOME="$work/share" "$exe" install-desktop --user
entry="$work/share/applications/hapticloud.desktop"
grep -qF "Exec=$exe app %f" "$entry"
if command -v desktop-file-validate >/dev/null; then desktop-file-validate "$entry"; fi
echo "smoke: bundle $(du -sh "$bundle" | cut -f1) at $bundle; all steps passed"
