#!/usr/bin/env bash
# Install navcrafter into ./.venv on a Debian machine (CPU build of torch).
#   bash deploy/local/setup.sh          # the product
#   bash deploy/local/setup.sh test     # the product and its test tools
# Re-running is cheap: nothing is reinstalled unless pyproject.toml or the constraints changed.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
extras="${1:-}"

PY="${PYTHON:-python3}"
"$PY" -c 'import sys; sys.exit(sys.version_info[:2] < (3, 11))' \
  || { echo "navcrafter needs Python >= 3.11 (found $("$PY" --version 2>&1)); set PYTHON=..." >&2; exit 1; }

# Open3D loads libusb-1.0 at import time (Debian package libusb-1.0-0).
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get install -y -q --no-install-recommends libusb-1.0-0 >/dev/null \
    || { $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q --no-install-recommends libusb-1.0-0 >/dev/null; }
fi

# The test tools: the browser tests (tests/browser.py) screenshot pages with headless Chromium (Debian's chromium).
if [[ ",$extras," == *,test,* ]] && ! command -v chromium >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get install -y -q --no-install-recommends chromium >/dev/null \
    || { $SUDO apt-get update -q >/dev/null && $SUDO apt-get install -y -q --no-install-recommends chromium >/dev/null; }
fi

[ -x .venv/bin/python ] || "$PY" -m venv .venv
stamp=".venv/.installed-${extras:-base}-$(cat pyproject.toml deploy/constraints.txt | sha256sum | cut -c1-16)"
if [ ! -e "$stamp" ]; then
  echo "installing navcrafter${extras:+[$extras]} into .venv (first time: a few minutes)..."
  .venv/bin/pip install -q --disable-pip-version-check -c deploy/constraints.txt -e ".${extras:+[$extras]}"
  rm -f .venv/.installed-"${extras:-base}"-*
  touch "$stamp"
fi
