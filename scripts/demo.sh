#!/usr/bin/env bash
# Sets up the environment and runs the main job on the bundled sample bag
# (bags/sample_human: 60 frames of a simulated full body at 320x240 with Kinect noise):
# `skel-extract replay` starts the three ROS nodes (registration, accumulator, joint
# estimation) as separate processes talking over DDS on localhost, feeds them the bag,
# records every output topic to output.mcap and writes skeleton.json / registered.npz /
# skeleton.png; then both are evaluated against the bag's ground truth. Results go to
# out/sample_human/ (or the directory given as $1).
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
"$CLI" info "$SAMPLE"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
rm -rf "$OUT/output.mcap" "$OUT/logs"   # replay never overwrites a recording
"$CLI" replay "$SAMPLE" --out "$OUT" --rate 0
"$CLI" evaluate --gt "$SAMPLE/gt.npz" --pred "$OUT/skeleton.json" --registered "$OUT/registered.npz"
