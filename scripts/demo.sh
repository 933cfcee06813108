#!/usr/bin/env bash
# Sets up the environment and runs the main job on the bundled sample bag
# (bags/sample_human: 60 frames of a simulated full body at 320x240 with Kinect noise).
# Results go to out/sample_human/ (or the directory given as first argument).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup_env.sh"
VENV="${SKEL_VENV:-$ROOT/.venv}"
OUT="${1:-$ROOT/out/sample_human}"
SAMPLE="$ROOT/bags/sample_human"
CLI="$VENV/bin/skel-extract"

if [ ! -f "$SAMPLE/metadata.yaml" ]; then
  echo "[demo] sample bag missing: simulating it" >&2
  "$CLI" simulate --subject human --frames 60 --seed 7 --out "$SAMPLE"
fi
mkdir -p "$OUT"
"$CLI" info "$SAMPLE"
rm -rf "$OUT/resimulated"
"$CLI" simulate --subject human --frames 60 --seed 7 --out "$OUT/resimulated"
