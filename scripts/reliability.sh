#!/usr/bin/env bash
# Reliability figures of dist4d against kills, shared stores, damage, full disks, races, hostile
# inputs and misbehaving workers (issues 20 and 41; docs/BENCHMARKS.md, "Reliability").
#
#   cargo build --release && scripts/reliability.sh [TRIALS] [WORKDIR] [CHECKS]
#
# TRIALS (default 20) is the number of trials of the checks that draw something at random (kills,
# tamper, disk-full); WORKDIR (default a new temporary folder) holds the synthetic dataset, stores
# and folders, and logs/ with every run's output; CHECKS is a comma list of check names or numbers
# (default all), e.g. `scripts/reliability.sh 5 /tmp/rel tamper,newer,9`. Each check prints one
# summary line with its figures (`FAIL:` in front when a figure is not what dist4d guarantees);
# the exit code is 1 when any check failed. Every run is the real binary (target/release/dist4d)
# on a `dist4d synth` dataset of 4 scenes x 4 keyframes at 480x270, `--jobs 1` unless said.
#
#  1. kills: TRIALS times, two shard processes (`--shard 0/2`, `1/2`) run the curation pipeline
#     at once on one store into one folder and are SIGKILLed together (the dist4d processes, not
#     a shell around them) at a random moment of the run. Right after the kill, every exported file is checked to be whole (absent, or
#     byte-identical to a single-process reference: no partial file); then both shards are rerun,
#     and the folder must equal the reference byte for byte (index.json too), with no temp file
#     left in the store or the folder.
#  2. sharing: two processes run the whole pipeline at once on one store: together they must
#     execute each task once (claims), not each do all of it.
#  3. corruption: four shard processes at once on one fresh store, then blobs are damaged (half
#     bit-flipped, half truncated) and the four run again into a new folder: every damaged blob
#     that is read must be detected and recomputed, and the folder must equal the reference.
#  4. tamper: TRIALS times, a copy of a complete store (and of its folder) gets one bit flipped at
#     a random offset in the middle half of its largest `ac/*.seg` segment; `dist4d verify --store`
#     must report it (exit 1), and a rerun must execute about one task (the records after the
#     damaged one are recovered) and give the reference's bytes.
#  5. newer: a copy of a complete store has one segment's header rewritten `D4SEG01` ->
#     `D4SEG09` (a newer dist4d's format): a run must refuse (non-zero exit, naming a newer
#     dist4d), and `dist4d gc` must leave that file as it was.
#  6. disk-full: TRIALS runs on a 3 MiB tmpfs (`mount -t tmpfs`, needs root; skipped with the
#     reason when the mount fails), half with the store on it, half with the output folder on it:
#     each must exit 1, be recorded `failed` by `dist4d runs --json` with an error naming the
#     full disk, and leave no temp file in the store's `tmp/` or the folder's `.dist4d-tmp/`.
#  7. race: 20 times, two different pipelines (lidar_depth and curation, on a store that has all
#     their tasks) are released at the same instant (a FIFO as the starting gun) into one new
#     `--out`: never may both exit 0, nor may the folder hold files of the pipeline its manifest
#     does not name.
#  8. hostile: a copy of the dataset with one LiDAR sweep replaced by a FIFO and one camera image
#     by a symlink to /dev/zero: the run must end (`timeout 120`), exit 1, and name both files.
#  9. stop: 3 times, occupancy.ron with an exact occupancy that takes minutes per frame
#     (`exact.samples=16`, a 0.1 m grid), `--jobs 2`, SIGTERM after 6 s: seconds from the signal
#     to the exit (the max is printed) and the exit code (143).
# 10. worker: the curation pipeline with `complete` served by workers/protocol_test_worker.py
#     (`deadline_s: 5`) that closes its stdout, before its hello (`--close-stdout-at-start`, all
#     96 items) and on every request (`--every close-stdout`, the 6 items of one frame): the run
#     must end (`timeout 300`; SIGKILL 120 s after its SIGTERM), exit 1, and leave no worker
#     process (nor the `sleep` each starts in its process group).
set -euo pipefail
trials=${1:-20}
work=${2:-$(mktemp -d)}
checks=${3:-all}
repo=$(cd "$(dirname "$0")/.." && pwd)
bin=$repo/target/release/dist4d
[ -x "$bin" ] || { echo "build first: cargo build --release" >&2; exit 2; }
mkdir -p "$work/logs"
cd "$work"
[ -d data ] || "$bin" synth --out data --scenes 4 --keyframes 4 --width 480 --height 270 >/dev/null 2>&1

# Whether check number $1, named $2, is asked for.
want() { [ "$checks" = all ] || [[ ",$checks," == *",$1,"* ]] || [[ ",$checks," == *",$2,"* ]]; }
failed=0
# Prints a check's summary line: `FAIL: ` in front when $1 is not `ok`.
summary() { # ok|fail LINE
  if [ "$1" = ok ]; then echo "$2"; else echo "FAIL: $2"; failed=1; fi
}

pipeline() { # FILE STORE OUT [args...]
  local file=$1 store=$2 out=$3; shift 3
  "$bin" run "$file" --set dataset.root="$work/data" --cache "$store" --out "$out" --progress off "$@"
}
run() { # STORE OUT [args...]: the curation pipeline, one thread
  local store=$1 out=$2; shift 2
  pipeline "$repo/pipelines/curation.ron" "$store" "$out" --jobs 1 "$@"
}
# Starts a run in the background with its output to LOG, and sets `pid` to the pid of dist4d
# itself: `run .. &` would give the pid of a subshell, and a signal sent there would not reach
# dist4d.
spawn() { # LOG FILE STORE OUT [args...]
  local log=$1 file=$2 store=$3 out=$4; shift 4
  "$bin" run "$file" --set dataset.root="$work/data" --cache "$store" --out "$out" --progress off "$@" >"$log" 2>&1 &
  pid=$!
}
# Files of a folder that are not dist4d's bookkeeping, as `sha256 path` lines.
sums() { (cd "$1" && find . -type f ! -path './.dist4d*' -print0 | sort -z | xargs -0 -r sha256sum); }
secs() { awk -v a="$1" -v b="$(date +%s.%N)" 'BEGIN { printf "%.2f", b - a }'; }
# A figure of the latest run recorded in a store: `executed` (tasks, summed over its stages),
# `status`, or `error` (its first failure: what stopped it, when something did).
last_run() { # STORE executed|status|error
  "$bin" runs --cache "$1" --json | python3 -c '
import json, sys
runs = json.load(sys.stdin)
run = max(runs, key=lambda r: (r["started"], r["id"])) if runs else {}
what = sys.argv[1]
if what == "executed":
    print(sum(s["executed"] for s in run.get("stages", [])))
elif what == "status":
    print(run.get("status", "none"))
else:
    failures = run.get("failures") or [{}]
    print(failures[0].get("error", "").replace("\n", " ")[:200])
' "$2"
}
last_executed() { last_run "$1" executed; }
flip_bit() { # FILE OFFSET: flips the lowest bit of the byte at OFFSET
  local f=$1 off=$2 byte
  byte=$(dd if="$f" bs=1 skip="$off" count=1 2>/dev/null | od -An -tu1 | tr -d ' ')
  printf "$(printf '\\%03o' $((byte ^ 1)))" | dd of="$f" bs=1 seek="$off" count=1 conv=notrunc 2>/dev/null
}

# The single-process reference (store and folder) most checks compare with.
ref_sums=
reference() {
  [ -n "$ref_sums" ] && return
  rm -rf ref ref-store
  run ref-store ref >/dev/null
  ref_sums=$(sums ref)
  nfiles=$(echo "$ref_sums" | wc -l)
}

if want 1 kills; then
  reference
  # The time of a two-shard run, to draw kill moments from.
  rm -rf store out
  t0=$(date +%s.%N)
  run store out --shard 0/2 >/dev/null & run store out --shard 1/2 >/dev/null & wait
  span=$(secs "$t0")
  echo "two-shard run: ${span}s, $nfiles files"
  partial=0; mismatched=0; leftover=0
  for t in $(seq 1 "$trials"); do
    rm -rf store out
    at=$(awk -v s="$RANDOM$t" -v T="$span" 'BEGIN { srand(s); printf "%.3f", rand() * T }')
    spawn /dev/null "$repo/pipelines/curation.ron" store out --jobs 1 --shard 0/2; a=$pid
    spawn /dev/null "$repo/pipelines/curation.ron" store out --jobs 1 --shard 1/2; b=$pid
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
  verdict=$( [ $((partial + mismatched + leftover)) = 0 ] && echo ok || echo fail )
  summary "$verdict" "kills: $trials trials, $partial partial files, $mismatched reruns not byte-identical, $leftover temp files left"
fi

if want 2 sharing; then
  reference
  # Two processes running the whole pipeline at once on one store share the work (claims).
  rm -rf store out
  t0=$(date +%s.%N)
  run store out >/dev/null 2>&1 & run store out >/dev/null 2>&1 & wait
  both=$(secs "$t0")
  each=$("$bin" runs --cache store | grep -o '[0-9]* executed' | awk '{s = s " " $1} END {print s}')
  total=$(echo "$each" | awk '{for (i = 1; i <= NF; i++) s += $i} END {print s + 0}')
  once=$(last_executed ref-store)
  [ "$(sums out)" = "$ref_sums" ] && same=identical || same=DIFFERENT
  verdict=$( [ "$total" = "$once" ] && [ $same = identical ] && echo ok || echo fail )
  summary "$verdict" "sharing: two unsharded processes at once: ${both}s, tasks executed per process:$each (one process: $once); outputs $same"
fi

if want 3 corruption; then
  reference
  # Corruption, with four shard processes at once.
  rm -rf store out out2
  t0=$(date +%s.%N)
  for i in 0 1 2 3; do run store out --shard $i/4 >/dev/null & done; wait
  four=$(secs "$t0")
  executed=$("$bin" runs --cache store --json | grep -o '"executed": [0-9]*' | awk '{s += $2} END {print s}')
  once=$(last_executed ref-store)
  [ "$(sums out)" = "$ref_sums" ] && same=identical || same=DIFFERENT
  echo "four shards at once: ${four}s, $executed tasks executed in all (one process: $once), outputs $same"
  mapfile -t blobs < <(find store/cas -type f -size +1k | sort | awk 'NR % 7 == 0' | head -20)
  for i in "${!blobs[@]}"; do
    f=${blobs[$i]}
    if [ $((i % 2)) = 0 ]; then # flip one bit in the middle
      flip_bit "$f" $(( $(stat -c %s "$f") / 2 ))
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
  [ "$(sums out2)" = "$ref_sums" ] && same2=identical || same2=DIFFERENT
  verdict=$( [ "$executed" = "$once" ] && [ $same = identical ] && [ $same2 = identical ] && echo ok || echo fail )
  summary "$verdict" "corruption: ${#blobs[@]} blobs damaged (half bit flips, half truncations); $detected read and detected, $unread not read by this run; $recomputed tasks recomputed; outputs $same2 to one process"
fi

if want 4 tamper; then
  reference
  # A copy of the complete store and its folder, rerun untouched: what a rerun executes anyway.
  rm -rf tamper-store tamper-out
  cp -a ref-store tamper-store; cp -a ref tamper-out
  run tamper-store tamper-out >"$work/logs/tamper-baseline.log" 2>&1
  baseline=$(last_executed tamper-store)
  reported=0; most=0; total=0; different=0; runs_failed=0
  for t in $(seq 1 "$trials"); do
    rm -rf tamper-store tamper-out
    cp -a ref-store tamper-store; cp -a ref tamper-out
    seg=$(find tamper-store/ac -name '*.seg' -printf '%s %p\n' | sort -n | tail -1 | cut -d' ' -f2)
    size=$(stat -c %s "$seg")
    off=$(awk -v s="$RANDOM$t" -v n="$size" 'BEGIN { srand(s); printf "%d", n / 4 + rand() * n / 2 }')
    flip_bit "$seg" "$off"
    vrc=0; "$bin" verify --store --cache tamper-store >"$work/logs/tamper-verify-$t.log" 2>&1 || vrc=$?
    says=$(grep -c "$(basename "$seg")" "$work/logs/tamper-verify-$t.log" || true)
    if [ "$vrc" = 1 ] && [ "$says" -gt 0 ]; then reported=$((reported + 1)); fi
    rrc=0; run tamper-store tamper-out >"$work/logs/tamper-run-$t.log" 2>&1 || rrc=$?
    [ "$rrc" = 0 ] || runs_failed=$((runs_failed + 1))
    n=$(last_executed tamper-store)
    total=$((total + n)); [ "$n" -gt "$most" ] && most=$n
    [ "$(sums tamper-out)" = "$ref_sums" ] || different=$((different + 1))
    echo "trial $t: bit flipped at byte $off of $size of $(basename "$seg"); verify exit $vrc, names the segment: $( [ "$says" -gt 0 ] && echo yes || echo NO ); rerun exit $rrc, $n tasks executed"
  done
  verdict=$( [ "$reported" = "$trials" ] && [ "$most" -le $((baseline + 2)) ] && [ $((different + runs_failed)) = 0 ] && echo ok || echo fail )
  summary "$verdict" "tamper: $trials trials of one bit flipped in a segment of $(find ref-store/ac -name '*.seg' | wc -l) ($nfiles files, $(last_executed ref-store) tasks); verify --store reported $reported of $trials (exit 1); rerun executed $total tasks in all, at most $most per trial (untampered copy: $baseline); $runs_failed reruns failed, $different outputs not byte-identical"
fi

if want 5 newer; then
  reference
  rm -rf newer-store newer-out
  cp -a ref-store newer-store; cp -a ref newer-out
  seg=$(find newer-store/ac -name '*.seg' | sort | head -1)
  head -c 8 "$seg" | grep -q "^D4SEG01$" || echo "note: $seg does not begin with D4SEG01"
  printf 'D4SEG09\n' | dd of="$seg" bs=1 seek=0 count=8 conv=notrunc 2>/dev/null
  before=$(sha256sum "$seg")
  rrc=0; run newer-store newer-out >"$work/logs/newer-run.log" 2>&1 || rrc=$?
  names=$(grep -c -i "newer dist4d" "$work/logs/newer-run.log" || true)
  grc=0; "$bin" gc --cache newer-store >"$work/logs/newer-gc.log" 2>&1 || grc=$?
  after=$(sha256sum "$seg" 2>/dev/null || echo missing)
  [ "$before" = "$after" ] && kept="left as it was" || kept="CHANGED OR DELETED"
  verdict=$( [ "$rrc" != 0 ] && [ "$names" -gt 0 ] && [ "$before" = "$after" ] && echo ok || echo fail )
  summary "$verdict" "newer: a segment headed D4SEG09: run exit $rrc, $( [ "$names" -gt 0 ] && echo names || echo DOES NOT NAME ) a newer dist4d ($(grep -i -m1 "newer dist4d" "$work/logs/newer-run.log" | cut -c1-240)); gc exit $grc, the segment $kept"
fi

if want 6 disk-full; then
  full=$work/tmpfs
  mkdir -p "$full"
  if ! mountpoint -q "$full" && ! mount -t tmpfs -o size=3M tmpfs "$full" 2>"$work/logs/mount.log"; then
    echo "disk-full: skipped: mount -t tmpfs failed: $(head -1 "$work/logs/mount.log")"
  else
    trap 'umount "$full" 2>/dev/null || true' EXIT
    bad_exit=0; not_failed=0; no_space=0; leftover=0; codes=
    for t in $(seq 1 "$trials"); do
      rm -rf "${full:?}"/* full-store full-out
      if [ $((t % 2)) = 1 ]; then store=$full/store; out=full-out; where=store
      else store=full-store; out=$full/out; where=folder; fi
      rc=0; run "$store" "$out" >"$work/logs/full-run-$t.log" 2>&1 || rc=$?
      codes="$codes $rc"
      [ "$rc" = 1 ] || bad_exit=$((bad_exit + 1))
      status=$(last_run "$store" status || echo "no record")
      error=$(last_run "$store" error || true)
      [ "$status" = failed ] || not_failed=$((not_failed + 1))
      grep -q -i "no space left" <<<"$error" || no_space=$((no_space + 1))
      left=$(find "$store/tmp" "$out/.dist4d-tmp" -type f 2>/dev/null | wc -l)
      leftover=$((leftover + left))
      echo "trial $t ($where on the 3 MiB tmpfs): exit $rc, recorded $status: $error; $left temp files left"
    done
    rm -rf "${full:?}"/*
    umount "$full"; trap - EXIT
    verdict=$( [ $((bad_exit + not_failed + no_space + leftover)) = 0 ] && echo ok || echo fail )
    summary "$verdict" "disk-full: $trials runs on a 3 MiB tmpfs (store or folder on it): exit codes$codes; $not_failed not recorded failed, $no_space without the disk's error in the record, $leftover temp files left"
  fi
fi

if want 7 race; then
  reference
  ld=$repo/pipelines/lidar_depth.ron
  # Each pipeline's own folder, and a store that has the tasks of both (so the race is the claim
  # of the folder and the export, not the work).
  rm -rf race-store race-ld race-cur
  pipeline "$ld" race-store race-ld --jobs 1 >/dev/null
  run race-store race-cur >/dev/null
  ld_sums=$(sums race-ld)
  both_ok=0; mixed=0; neither=0; won_ld=0; won_cur=0
  for t in $(seq 1 20); do
    rm -rf race-out gun; mkfifo gun
    # Both block opening the FIFO until it is opened for writing, and go at its end of file.
    ( read -r _ <gun || true; exec "$bin" run "$ld" --set dataset.root="$work/data" --cache race-store --out race-out --progress off --jobs 1 ) >"$work/logs/race-ld-$t.log" 2>&1 & a=$!
    ( read -r _ <gun || true; exec "$bin" run "$repo/pipelines/curation.ron" --set dataset.root="$work/data" --cache race-store --out race-out --progress off --jobs 1 ) >"$work/logs/race-cur-$t.log" 2>&1 & b=$!
    sleep 0.3; : >gun
    ra=0; wait $a || ra=$?; rb=0; wait $b || rb=$?
    owner=$(head -1 race-out/.dist4d-manifest 2>/dev/null | awk '{print $3}')
    case $owner in lidar_depth) won_ld=$((won_ld + 1));; curation) won_cur=$((won_cur + 1));; esac
    if [ "$ra" = 0 ] && [ "$rb" = 0 ]; then both_ok=$((both_ok + 1)); fi
    if [ "$ra" != 0 ] && [ "$rb" != 0 ]; then neither=$((neither + 1)); fi
    # A file of the other pipeline: one only it writes, or one both write holding its bytes
    # where the owner's differ.
    here=$(sums race-out)
    own=$( [ "$owner" = lidar_depth ] && echo "$ld_sums" || echo "$ref_sums" )
    foreign=$(comm -23 <(echo "$here" | sed '/^$/d' | sort) <(echo "$own" | sort) | wc -l)
    if [ "$foreign" -gt 0 ]; then mixed=$((mixed + 1)); fi
    echo "try $t: lidar_depth exit $ra, curation exit $rb, folder owned by ${owner:-nobody}, $(echo "$here" | sed '/^$/d' | wc -l) files, $foreign not the owner's"
  done
  rm -f gun
  verdict=$( [ $((both_ok + mixed)) = 0 ] && echo ok || echo fail )
  summary "$verdict" "race: 20 tries of lidar_depth and curation released at once into a new --out: both exited 0 in $both_ok, neither in $neither; the folder went to lidar_depth $won_ld times, curation $won_cur; held files of both in $mixed"
fi

if want 8 hostile; then
  rm -rf hostile-data hostile-store hostile-out
  cp -a data hostile-data
  lidar=$(find hostile-data/samples -path '*LIDAR_TOP*' -type f | sort | head -1)
  image=$(find hostile-data/samples -path '*CAM_FRONT/*' -type f | sort | head -1)
  rm "$lidar" "$image"; mkfifo "$lidar"; ln -s /dev/zero "$image"
  t0=$(date +%s.%N)
  rc=0; timeout 120 "$bin" run "$repo/pipelines/curation.ron" --set dataset.root="$work/hostile-data" \
    --cache hostile-store --out hostile-out --progress off >"$work/logs/hostile.log" 2>&1 || rc=$?
  took=$(secs "$t0")
  has_lidar=$(grep -c "$(basename "$lidar")" "$work/logs/hostile.log" || true)
  has_image=$(grep -c "$(basename "$image")" "$work/logs/hostile.log" || true)
  verdict=$( [ "$rc" = 1 ] && [ "$has_lidar" -gt 0 ] && [ "$has_image" -gt 0 ] && echo ok || echo fail )
  summary "$verdict" "hostile: a FIFO for $(basename "$lidar"), a symlink to /dev/zero for $(basename "$image"): run ended in ${took}s with exit $rc$( [ "$rc" = 124 ] && echo ' (timeout)' || true); the FIFO named $( [ "$has_lidar" -gt 0 ] && echo yes || echo NO ), the /dev/zero image named $( [ "$has_image" -gt 0 ] && echo yes || echo NO )"
fi

if want 9 stop; then
  latencies=; codes=; statuses=; most=0
  for t in 1 2 3; do
    rm -rf stop-store stop-out
    spawn "$work/logs/stop-$t.log" "$repo/pipelines/occupancy.ron" stop-store stop-out --jobs 2 --set exact.samples=16 \
      --set 'exact.grid=(range: [-40.0, -40.0, -1.0, 40.0, 40.0, 5.4], voxel: 0.1, lift: 0.0)'
    p=$pid
    sleep 6
    kill -TERM $p
    t0=$(date +%s.%N)
    # Bounded: a run still going after 300 s is killed and counted as such.
    while kill -0 $p 2>/dev/null && [ "$(secs "$t0" | cut -d. -f1)" -lt 300 ]; do sleep 0.05; done
    took=$(secs "$t0")
    if kill -0 $p 2>/dev/null; then kill -9 $p; echo "trial $t: still running 300 s after SIGTERM: killed"; fi
    rc=0; wait $p || rc=$?
    # 143 is also what a process killed by the signal gives: the record tells a clean stop.
    status=$(last_run stop-store status || echo "no record")
    echo "trial $t: exit $rc ${took}s after SIGTERM, recorded $status; $(grep -m1 '^stopped:' "$work/logs/stop-$t.log" || echo 'no stop message')"
    latencies="$latencies ${took}s"; codes="$codes $rc"; statuses="$statuses $status"
    most=$(awk -v a="$most" -v b="$took" 'BEGIN { print (b > a) ? b : a }')
  done
  verdict=$( [ "$codes" = " 143 143 143" ] && [ "$statuses" = " interrupted interrupted interrupted" ] \
    && awk -v m="$most" 'BEGIN { exit !(m < 10) }' && echo ok || echo fail )
  summary "$verdict" "stop: occupancy with a minutes-long exact occupancy, SIGTERM after 6 s, 3 times: exit after$latencies (max ${most}s), exit codes$codes, recorded$statuses"
fi

if want 10 worker; then
  script=$repo/workers/protocol_test_worker.py
  results=; bad=0
  for mode in "--close-stdout-at-start" "--every close-stdout"; do
    name=${mode//[- ]/}
    # Every request failing costs each item its tries, with restart pauses growing to 30 s: the
    # second mode runs the 6 items of one frame only.
    only=(); [ "$mode" = "--close-stdout-at-start" ] || only=(--scenes synth-0000 --limit 1)
    pids=$work/logs/worker-$name.pids
    rm -rf worker-store worker-out "$pids" "$pids.requests"
    args="\"$script\", \"--op\", \"complete_depth\", \"--pid-file\", \"$pids\""
    for a in $mode; do args="$args, \"$a\""; done
    t0=$(date +%s.%N)
    rc=0; timeout -k 120 300 "$bin" run "$repo/pipelines/curation.ron" "${only[@]}" --set dataset.root="$work/data" \
      --cache worker-store --out worker-out --progress off --set "complete.worker=Some((program: \"python3\", args: [$args], deadline_s: 5))" \
      >"$work/logs/worker-$name.log" 2>&1 || rc=$?
    took=$(secs "$t0")
    sleep 1 # SIGKILL takes a moment to end a process
    left=$(pgrep -f "$script" | wc -l || true)
    # The workers and the `sleep` each started in its group, from the pid file: alive, not zombies.
    alive=0
    for pid in $(cat "$pids" 2>/dev/null); do
      state=$(awk '{print $3}' "/proc/$pid/stat" 2>/dev/null || true)
      if [ -n "$state" ] && [ "$state" != Z ]; then alive=$((alive + 1)); fi
    done
    started=$(wc -l <"$pids" 2>/dev/null || echo 0)
    closed=$(grep -c "closed its stdout" "$work/logs/worker-$name.log" || true)
    if ! { [ "$rc" = 1 ] && [ "$left" = 0 ] && [ "$alive" = 0 ]; }; then bad=$((bad + 1)); fi
    late=; if [ "$rc" = 124 ] || [ "$rc" = 137 ]; then late=" (timeout: SIGTERM at 300 s, exit $(awk -v t="$took" 'BEGIN { printf "%.1f", t - 300 }') s later)"; fi
    results="$results; $mode ($( [ ${#only[@]} = 0 ] && echo "96 items" || echo "6 items")): ended in ${took}s, exit $rc$late, $started workers started, $closed lines say 'closed its stdout', $left worker processes and $alive of their process groups left"
    # Leave nothing behind even when the check fails.
    for pid in $(cat "$pids" 2>/dev/null); do kill -9 "$pid" 2>/dev/null || true; done
  done
  summary "$( [ $bad = 0 ] && echo ok || echo fail )" "worker: a worker that closes its stdout, deadline_s: 5${results}"
fi

exit $failed
