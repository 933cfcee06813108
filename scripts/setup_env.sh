#!/usr/bin/env bash
# Prepares everything skel_extract_ros needs on a fresh Debian machine (Python 3.11, root):
#   - the Debian package libusb-1.0-0 that Open3D's wheel links against, when missing;
#   - a virtual environment (.venv, or $SKEL_VENV) with the pinned runtime, ROS-wheel and
#     test dependencies, and this package installed in editable mode.
# Idempotent: a stamp with the hash of the requirement files skips pip when nothing changed.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${SKEL_VENV:-$ROOT/.venv}"
PYTHON_BIN="${PYTHON:-}"

log() { echo "[setup] $*" >&2; }

# --- system library for Open3D -------------------------------------------------------------
# (grep reads all of ldconfig's output: with -q it stops early, ldconfig dies of SIGPIPE and
# pipefail calls the library missing, so apt ran on every call)
if ! ldconfig -p 2>/dev/null | grep 'libusb-1.0.so.0' >/dev/null; then
  log "installing Debian package libusb-1.0-0 (needed by Open3D)"
  SUDO=""
  if [ "$(id -u)" != "0" ]; then SUDO="sudo"; fi
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq --no-install-recommends libusb-1.0-0 >/dev/null
fi

# --- interpreter: the ROS Jazzy wheels are built for CPython 3.11 ------------------------------
if [ -z "$PYTHON_BIN" ]; then
  for candidate in python3.11 python3; do
    if command -v "$candidate" >/dev/null 2>&1; then PYTHON_BIN="$candidate"; break; fi
  done
fi
if ! "$PYTHON_BIN" -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)'; then
  echo "[setup] error: Python 3.11 is required (found $("$PYTHON_BIN" --version 2>&1)); set PYTHON=/path/to/python3.11" >&2
  exit 1
fi

# --- virtual environment ---------------------------------------------------------------------
if [ ! -x "$VENV/bin/python" ]; then
  log "creating virtual environment in $VENV"
  "$PYTHON_BIN" -m venv "$VENV"
fi

STAMP="$VENV/.skel_extract_ros.stamp"
WANT="$(cat "$ROOT"/requirements*.txt "$ROOT/setup.py" "$ROOT/setup.cfg" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  log "installing pinned dependencies (first run takes about a minute)"
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check \
      -r "$ROOT/requirements.txt" -r "$ROOT/requirements-ros.txt" -r "$ROOT/requirements-dev.txt"
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps -e "$ROOT"
  echo "$WANT" > "$STAMP"
fi
log "environment ready: $VENV"
