#!/usr/bin/env bash
# A single-node Slurm cluster on this machine, for dist4d's cluster tests (issue 20): Debian's
# slurm-wlm (22.05) with munge, started without systemd, everything under one folder.
#
#   scripts/slurm-single-node.sh start DIR   # installs the packages when missing (needs root),
#                                            # writes DIR/slurm.conf, starts munged, slurmctld, slurmd
#   export SLURM_CONF=DIR/slurm.conf         # then sbatch / squeue / scancel as usual
#   scripts/slurm-single-node.sh stop DIR    # stops the daemons it started, by PID
#
# SLURM_PORT_BASE (default 6817) sets slurmctld's port, slurmd's is the next: clusters started
# at once (tests, a user's own) need different ones.
#
# Exit 3 when Slurm cannot be had here (no root to install it): callers skip, saying so.
set -euo pipefail
cmd=${1:?start or stop}
dir=$(mkdir -p "${2:?a folder}" && cd "$2" && pwd)

stop() {
  for pid in "$dir/slurmd.pid" "$dir/slurmctld.pid" "$dir/munged.pid"; do
    [ -f "$pid" ] && kill "$(cat "$pid")" 2>/dev/null || true
    rm -f "$pid"
  done
}

if [ "$cmd" = stop ]; then
  stop
  exit 0
fi
[ "$cmd" = start ] || { echo "usage: $0 start|stop DIR" >&2; exit 2; }

if ! command -v slurmctld >/dev/null || ! command -v munged >/dev/null; then
  if [ "$(id -u)" != 0 ]; then
    echo "SKIPPED: slurm-wlm and munge are not installed and this is not root" >&2
    exit 3
  fi
  if ! { apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm munge >/dev/null; }; then
    echo "SKIPPED: slurm-wlm and munge could not be installed (apt-get failed)" >&2
    exit 3
  fi
fi

host=$(hostname)
cpus=$(nproc)
mem=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 * 8 / 10 ))
mkdir -p "$dir/state" "$dir/spool" "$dir/munge"
cat > "$dir/slurm.conf" <<CONF
ClusterName=dist4d
SlurmctldHost=$host
SlurmctldPort=${SLURM_PORT_BASE:-6817}
SlurmdPort=$(( ${SLURM_PORT_BASE:-6817} + 1 ))
SlurmUser=$(id -un)
AuthType=auth/munge
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
ReturnToService=2
NodeName=$host CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=main Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF

# munge: its own key and socket under DIR, so nothing of the machine's is touched.
[ -f "$dir/munge/munge.key" ] || dd if=/dev/urandom of="$dir/munge/munge.key" bs=1024 count=1 2>/dev/null
chmod 700 "$dir/munge"; chmod 400 "$dir/munge/munge.key"
munged --force --key-file="$dir/munge/munge.key" --socket="$dir/munge/munge.socket" \
  --pid-file="$dir/munged.pid" --log-file="$dir/munged.log" --seed-file="$dir/munge/munge.seed"
export SLURM_CONF="$dir/slurm.conf"
# Slurm finds munge's socket through its auth options.
echo "AuthInfo=socket=$dir/munge/munge.socket" >> "$dir/slurm.conf"
slurmctld -f "$dir/slurm.conf"
slurmd -f "$dir/slurm.conf"
for _ in $(seq 1 50); do
  if sinfo -h -o %T 2>/dev/null | grep -q idle; then
    echo "slurm up: export SLURM_CONF=$dir/slurm.conf"
    exit 0
  fi
  sleep 0.2
done
echo "slurm did not come up; see $dir/slurmctld.log and $dir/slurmd.log" >&2
stop
exit 1
