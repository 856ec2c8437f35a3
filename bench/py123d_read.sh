#!/usr/bin/env bash
# The py123d reader's cost per image against the nuScenes reader on the same scene (issue 43's
# target: at most 1.2x). A synthetic scene at nuScenes size (6 keyframes, 1600x900) is converted
# by py123d itself (scripts/py123d_convert.py) into a log with JPEGs and IPC-zstd LiDAR in it and
# one that stores paths; every image, calibration, pose, box and sweep is then read 5 times by
# each reader (stages/datasets/examples/read_sources.rs), medians compared.
#
#   bench/py123d_read.sh [PY123D_PYTHON]     (default .venv-py123d/bin/python)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${1:-.venv-py123d/bin/python}
W=$(mktemp -d)
trap 'rm -rf "$W"' EXIT
cargo build -q --release --bin dist4d -p dist4d-datasets --example read_sources 2>/dev/null || cargo build -q --release
cargo build -q --release -p dist4d-datasets --example read_sources
./target/release/dist4d synth --out "$W/source" --keyframes 6 --seed 1 >/dev/null
"$PY" scripts/py123d_convert.py --nuscenes-root "$W/source" --out "$W/inlog" --keyframes --camera-storage jpeg --lidar-storage in_log >/dev/null
"$PY" scripts/py123d_convert.py --nuscenes-root "$W/source" --out "$W/paths" --keyframes --camera-storage path --lidar-storage path >/dev/null
median() { sort -n | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}'; }
run() { for _ in 1 2 3 4 5; do ./target/release/examples/read_sources "$@" | sed -E 's/.*: ([0-9.]+) ms per image.*/\1/'; done | median; }
native=$(run nuscenes "$W/source")
inlog=$(run py123d "$W/inlog")
paths=$(run py123d "$W/paths" "$W/source")
echo "ms per image (median of 5): nuScenes reader $native, py123d log (JPEG + IPC-zstd in the log) $inlog, py123d log (paths) $paths"
awk -v n="$native" -v a="$inlog" -v b="$paths" 'BEGIN { printf "ratio to the nuScenes reader: in the log %.2fx, paths %.2fx (target <= 1.2x)\n", a / n, b / n }'
