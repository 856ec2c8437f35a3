#!/usr/bin/env bash
# The real-data checks of issue 42: the shipped curation on the real recordings of
# ../shared/data, scored against the hand labels of tests/fixtures/real_labels
# (docs/BENCHMARKS.md, "Real images against hand labels").
#
#   cargo build --release && scripts/real_checks.sh [WORKDIR] [SHARED_DATA] [RUN ARGS...]
#
# WORKDIR (default a new temporary folder) holds the stores, exports and logs; SHARED_DATA
# (default ../shared/data) the recordings; RUN ARGS go to `dist4d run` (e.g. --set 'ego.rig="none"',
# which leaves the ego body to the estimate). Per dataset it prints, per labelled image and in all:
#   ego masked       labelled ego-body pixels at depth 0 (target >= 95%)
#   others masked    other pixels at depth 0 (target <= 0.5%)
#   sky at sky depth labelled sky pixels at the pipeline's sky depth, 100 m (target >= 95%)
#   bright not sky   labelled bright-structure pixels (white walls, soffits, signs) not at the
#                    sky depth (target >= 99%)
#   streak ratio     top third, sky excluded: share of vertically equal neighbours over
#                    horizontally equal ones (target <= 1.3 on every image)
set -euo pipefail
cd "$(dirname "$0")/.."
work=${1:-$(mktemp -d)}
shared=${2:-../shared/data}
shift $(( $# < 2 ? $# : 2 ))
mkdir -p "$work"
bin=target/release/dist4d
cargo build -q --release -p dist4d-stages --example label_scores
scores=target/release/examples/label_scores

# The shipped pipeline with another dataset (the readers give the same ports).
with_dataset() {
  python3 - "$1" "$2" <<'PY'
import sys
text = open(sys.argv[1]).read()
start = text.index("dataset: NuScenes(")
end = start + text[start:].index("\n    ),\n") + 7
print(text[:start] + "dataset: " + sys.argv[2] + "," + text[end:])
PY
}

for dataset in nuscenes-scene0061-kf0 dgp-scene02; do
  root=$(cd "$shared/$dataset" && pwd)
  case $dataset in
    nuscenes*) reader="NuScenes(root: \"$root\", version: \"v1.0-mini\")" ;;
    dgp*) reader="Dgp(root: \"$root\")" ;;
  esac
  # Beside the shipped pipeline, so that relative paths in it mean the same.
  pipeline=pipelines/.real-checks-$dataset.ron
  with_dataset pipelines/curation.ron "$reader" > "$pipeline"
  start=$(date +%s.%N)
  "$bin" run "$pipeline" --cache "$work/cache" --out "$work/$dataset" --progress off "$@" > "$work/$dataset.log" 2>&1 \
    || { rm -f "$pipeline"; echo "FAIL: the curation of $dataset failed; see $work/$dataset.log"; exit 1; }
  rm -f "$pipeline"
  echo "== $dataset (curation $(printf '%.1f' "$(echo "$(date +%s.%N) - $start" | bc)") s, exports in $work/$dataset)"
  "$scores" "$work/$dataset" "tests/fixtures/real_labels/$dataset"
done
