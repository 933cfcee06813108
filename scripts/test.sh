#!/usr/bin/env bash
# Sets up the environment (scripts/setup_env.sh) and runs the whole test suite.
# Extra arguments go to pytest, e.g. `bash scripts/test.sh -k evaluation`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup_env.sh"
VENV="${SKEL_VENV:-$ROOT/.venv}"
cd "$ROOT"
# Tests that start ROS nodes pick private domains themselves; keep DDS traffic on this host.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
exec "$VENV/bin/python" -m pytest -p no:cacheprovider "$@"
