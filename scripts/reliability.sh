#!/usr/bin/env bash
# Reliability figures of a store shared by shards (issue 20; docs/BENCHMARKS.md, "Reliability").
#
#   cargo build --release && scripts/reliability.sh [TRIALS] [WORKDIR]
#
# 1. Kills: TRIALS times (default 20), two shard processes (`--shard 0/2`, `1/2`) run the
#    curation pipeline at once on one store into one folder and are SIGKILLed together at a
#    random moment of the run. Right after the kill, every exported file is checked to be whole
#    (absent, or byte-identical to a single-process reference: no partial file); then both
#    shards are rerun, and the folder must equal the reference byte for byte (index.json too),
#    with no temp file left in the store or the folder.
# 2. Sharing: two processes run the whole pipeline at once on one store: together they must
#    execute each task once (claims), not each do all of it.
# 3. Corruption: four shard processes at once on one fresh store, then blobs are damaged (half
#    bit-flipped, half truncated) and the four run again into a new folder: every damaged blob
#    that is read must be detected and recomputed, and the folder must equal the reference.
set -euo pipefail
trials=${1:-20}
work=${2:-$(mktemp -d)}
repo=$(cd "$(dirname "$0")/.." && pwd)
bin=$repo/target/release/dist4d
[ -x "$bin" ] || { echo "build first: cargo build --release" >&2; exit 2; }
mkdir -p "$work"
cd "$work"
[ -d data ] || "$bin" synth --out data --scenes 4 --keyframes 4 --width 480 --height 270 >/dev/null 2>&1

run() { # STORE OUT [args...]
  local store=$1 out=$2; shift 2
  "$bin" run "$repo/pipelines/curation.ron" --set dataset.root="$work/data" --cache "$store" --out "$out" \
    --progress off --jobs 1 "$@"
}
# Files of a folder that are not dist4d's bookkeeping, as `sha256 path` lines.
sums() { (cd "$1" && find . -type f ! -path './.dist4d*' -print0 | sort -z | xargs -0 -r sha256sum); }

rm -rf ref ref-store
run ref-store ref >/dev/null
ref_sums=$(sums ref)
nfiles=$(echo "$ref_sums" | wc -l)

# The time of a two-shard run, to draw kill moments from.
rm -rf store out
t0=$(date +%s.%N)
run store out --shard 0/2 >/dev/null & run store out --shard 1/2 >/dev/null & wait
span=$(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%.2f", b - a }')
echo "two-shard run: ${span}s, $nfiles files"

partial=0; mismatched=0; leftover=0; redone=0
for t in $(seq 1 "$trials"); do
  rm -rf store out
  at=$(awk -v s="$RANDOM$t" -v T="$span" 'BEGIN { srand(s); printf "%.3f", rand() * T }')
  run store out --shard 0/2 >/dev/null 2>&1 & a=$!
  run store out --shard 1/2 >/dev/null 2>&1 & b=$!
  sleep "$at"
  kill -9 $a $b 2>/dev/null || true
  wait $a $b 2>/dev/null || true
  # Whole or absent: each file there now has the reference's bytes.
  here=$( [ -d out ] && sums out || true )
  bad=$(comm -23 <(echo "$here" | sed '/^$/d' | sort) <(echo "$ref_sums" | sort) | wc -l)
  present=$(echo "$here" | sed '/^$/d' | wc -l)
  partial=$((partial + bad))
  run store out --shard 0/2 >/dev/null 2>&1 & run store out --shard 1/2 >/dev/null 2>&1 & wait
  if [ "$(sums out)" != "$ref_sums" ] || ! cmp -s out/index.json ref/index.json; then
    mismatched=$((mismatched + 1))
  fi
  left=$(find store/tmp out/.dist4d-tmp -type f 2>/dev/null | wc -l)
  leftover=$((leftover + left))
  echo "trial $t: killed at ${at}s with $present of $nfiles files out, $bad not whole; rerun $( [ "$(sums out)" = "$ref_sums" ] && echo identical || echo DIFFERENT ), $left temp files left"
done
echo "kills: $trials trials, $partial partial files, $mismatched reruns not byte-identical, $leftover temp files left"

# Two processes running the whole pipeline at once on one store share the work (claims).
rm -rf store out
t0=$(date +%s.%N)
run store out >/dev/null 2>&1 & run store out >/dev/null 2>&1 & wait
both=$(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%.2f", b - a }')
each=$("$bin" runs --cache store | grep -o '[0-9]* executed' | awk '{s = s " " $1} END {print s}')
[ "$(sums out)" = "$ref_sums" ] && same=identical || same=DIFFERENT
echo "two unsharded processes at once: ${both}s, tasks executed per process:$each; outputs $same"

# Corruption, with four shard processes at once.
rm -rf store out out2
t0=$(date +%s.%N)
for i in 0 1 2 3; do run store out --shard $i/4 >/dev/null & done; wait
four=$(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%.2f", b - a }')
executed=$("$bin" runs --cache store --json | grep -o '"executed": [0-9]*' | awk '{s += $2} END {print s}')
once=$("$bin" runs --cache ref-store --json | grep -o '"executed": [0-9]*' | awk '{s += $2} END {print s}')
[ "$(sums out)" = "$ref_sums" ] && same=identical || same=DIFFERENT
echo "four shards at once: ${four}s, $executed tasks executed in all (one process: $once), outputs $same"
mapfile -t blobs < <(find store/cas -type f -size +1k | sort | awk 'NR % 7 == 0' | head -20)
for i in "${!blobs[@]}"; do
  f=${blobs[$i]}
  if [ $((i % 2)) = 0 ]; then # flip one bit in the middle
    size=$(stat -c %s "$f"); off=$((size / 2))
    byte=$(dd if="$f" bs=1 skip=$off count=1 2>/dev/null | od -An -tu1 | tr -d ' ')
    printf "$(printf '\\%03o' $((byte ^ 1)))" | dd of="$f" bs=1 seek=$off count=1 conv=notrunc 2>/dev/null
  else
    truncate -s $(( $(stat -c %s "$f") / 2 )) "$f"
  fi
done
damaged=$(for f in "${blobs[@]}"; do sha256sum "$f"; done)
for i in 0 1 2 3; do run store out2 --shard $i/4 >/dev/null 2>&1 & done; wait
recomputed=$("$bin" runs --cache store --json | grep -o '"recomputed": [0-9]*' | awk '{s += $2} END {print s}')
# A damaged blob that was read is gone (removed) or rewritten whole; one no task read is as it was.
detected=$( (echo "$damaged" | sha256sum -c --quiet 2>/dev/null || true) | wc -l)
unread=$(( ${#blobs[@]} - detected ))
[ "$(sums out2)" = "$ref_sums" ] && same=identical || same=DIFFERENT
echo "corruption: ${#blobs[@]} blobs damaged (half bit flips, half truncations); $detected read and detected, $unread not read by this run; $recomputed tasks recomputed; outputs $same to one process"
