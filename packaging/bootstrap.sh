#!/usr/bin/env bash
# Sets up everything hapticloud needs on a fresh Debian machine with Python 3.11 (run as root or
# with sudo available): the system libraries the wheels load, and the environment in .venv/ at
# the repository root. Safe to run again: it only does what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

# Open3D needs libusb; Qt's xcb plugin needs the xcb/xkb family; xvfb gives headless machines a
# display for the app and the GUI tests; desktop-file-validate checks the installed desktop entry
# (tests/app/test_packaging.py).
SYSTEM_PACKAGES=(
  libusb-1.0-0 libgl1 libegl1 libgomp1 libglib2.0-0 libdbus-1-3 libfontconfig1
  libxkbcommon0 libxkbcommon-x11-0 libxcb-cursor0 libxcb-icccm4 libxcb-image0 libxcb-keysyms1
  libxcb-randr0 libxcb-render-util0 libxcb-shape0 libxcb-xinerama0 libxcb-xkb1 libxcb-xfixes0
  libxrender1 libxi6 libsm6 libice6 xvfb xauth desktop-file-utils
)
missing=()
for pkg in "${SYSTEM_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "bootstrap: installing system packages: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PYTHON="${PYTHON:-}"
if [ -z "$PYTHON" ]; then
  for candidate in python3.11 python3.12 python3; do
    if command -v "$candidate" >/dev/null 2>&1 && "$candidate" -c 'import sys; sys.exit(not ((3, 11) <= sys.version_info[:2] < (3, 13)))'; then
      PYTHON="$candidate"; break
    fi
  done
fi
[ -n "$PYTHON" ] || { echo "bootstrap: need Python 3.11 or 3.12" >&2; exit 2; }

stamp=".venv/.hapticloud-installed"
inputs=(pyproject.toml setup.py)
[ -f requirements.lock ] && inputs+=(requirements.lock)
want="$(cat "${inputs[@]}" | sha256sum | cut -c1-16)"
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "bootstrap: installing Python packages into .venv"
  .venv/bin/python -m pip install -q --upgrade pip
  if [ -f requirements.lock ]; then
    .venv/bin/python -m pip install -q -c requirements.lock -e ".[app,hardware,record,study,test]"
  else
    .venv/bin/python -m pip install -q -e ".[app,hardware,record,study,test]"
  fi
  echo "$want" > "$stamp"
fi
