#!/usr/bin/env bash
# The workflow on a real one-node SLURM cluster on localhost (issue #9).
#
#   bash tests/cluster/run_slurm_test.sh [scratch dir, default /tmp/delta-slurm-test]
#   DELTA_TEST_REV=HEAD bash tests/cluster/run_slurm_test.sh   # a commit's code, not the working tree's
#   bash tests/cluster/run_slurm_test.sh /tmp/delta-slurm-test --retrain   # reuse both runs there, retrain only
#
# Installs Debian's slurmctld, slurmd and munge when missing (root), starts munged, slurmctld and
# slurmd with a slurm.conf written for this machine (its CPUs and memory, proctrack/pgid, task/none,
# select/cons_tres, no accounting database: job status comes from squeue), then runs
# tests/cluster/slurm_e2e.py: the tiny .test configuration through --executor slurm against a local
# run, and a training job scancel'ed mid-run that the profile's retry resumes from its checkpoint.
# The daemons it started are stopped on exit; the scratch dir is left for inspection.
set -euo pipefail

REPO=$(cd "$(dirname "$0")/../.." && pwd)
SCRATCH=${1:-/tmp/delta-slurm-test}
CLUSTER=$SCRATCH/cluster
# the default path: the jobstep plugin drops SLURM_* variables (SLURM_CONF too) before its srun
export SLURM_CONF=/etc/slurm/slurm.conf
SRC=$SCRATCH/src  # a snapshot of the code: the runs must not see edits made while they go
export PYTHONPATH=$SRC${PYTHONPATH:+:$PYTHONPATH}
STARTED_MUNGED=0

install_packages() {
  if command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v sbatch >/dev/null \
    && command -v munged >/dev/null; then
    return
  fi
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends slurmctld slurmd slurm-client munge
}

write_config() {
  mkdir -p "$CLUSTER"/{state,spool,log}
  local host cpus mem
  host=$(hostname -s)
  cpus=$(nproc)
  mem=$(($(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 - 1024))  # MB, leaving 1 GB to the system
  if [ -e "$SLURM_CONF" ] && ! grep -q '^ClusterName=delta-test' "$SLURM_CONF"; then
    mv "$SLURM_CONF" "$CLUSTER/slurm.conf.orig"  # put back on exit
  fi
  mkdir -p "$(dirname "$SLURM_CONF")"
  cat >"$SLURM_CONF" <<EOF
ClusterName=delta-test
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=local Nodes=ALL Default=YES MaxTime=INFINITE State=UP
ProctrackType=proctrack/pgid
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
MpiDefault=none
SwitchType=switch/none
ReturnToService=2
# no accounting database: sacct has nothing, squeue reports finished jobs for MinJobAge seconds
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
MinJobAge=600
KillWait=5
StateSaveLocation=$CLUSTER/state
SlurmdSpoolDir=$CLUSTER/spool
SlurmctldPidFile=$CLUSTER/slurmctld.pid
SlurmdPidFile=$CLUSTER/slurmd.pid
SlurmctldLogFile=$CLUSTER/log/slurmctld.log
SlurmdLogFile=$CLUSTER/log/slurmd.log
EOF
}

start_munge() {
  if munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    return  # a munged already answers
  fi
  [ -s /etc/munge/munge.key ] || mungekey --create --keyfile /etc/munge/munge.key
  mkdir -p /run/munge /var/log/munge /var/lib/munge
  chown munge:munge /etc/munge/munge.key /run/munge /var/log/munge /var/lib/munge
  chmod 0400 /etc/munge/munge.key
  runuser -u munge -- munged --pid-file=/run/munge/delta-test.pid
  STARTED_MUNGED=1
}

start_cluster() {
  start_munge
  slurmctld -f "$SLURM_CONF"
  slurmd -f "$SLURM_CONF"
  for _ in $(seq 60); do
    if [ "$(sinfo -h -o %T 2>/dev/null)" = idle ]; then
      sinfo
      return
    fi
    sleep 1
  done
  echo "the node never became idle:" >&2
  sinfo >&2 || true
  tail -20 "$CLUSTER"/log/*.log >&2
  exit 1
}

stop_pid() {
  [ -s "$1" ] || return 0
  local pid
  pid=$(cat "$1")
  kill "$pid" 2>/dev/null || true
  for _ in $(seq 20); do kill -0 "$pid" 2>/dev/null || return 0; sleep 0.5; done
  kill -9 "$pid" 2>/dev/null || true
}

stop_cluster() {
  scancel --user "$(id -un)" 2>/dev/null || true
  stop_pid "$CLUSTER/slurmd.pid"
  stop_pid "$CLUSTER/slurmctld.pid"
  [ "$STARTED_MUNGED" = 1 ] && stop_pid /run/munge/delta-test.pid
  rm -f "$SLURM_CONF"
  [ -e "$CLUSTER/slurm.conf.orig" ] && mv "$CLUSTER/slurm.conf.orig" "$SLURM_CONF"
  echo "slurm daemons stopped; logs in $CLUSTER/log"
}

snapshot() {
  rm -rf "$SRC" && mkdir -p "$SRC"
  if [ -n "${DELTA_TEST_REV:-}" ]; then
    git -C "$REPO" archive "$DELTA_TEST_REV" Snakefile rules workflow config .test delta | tar -x -C "$SRC"
    (cd "$REPO" && cp -r --parents tests/cluster "$SRC")  # the harness itself from the working tree
  else
    (cd "$REPO" && cp -r Snakefile rules workflow config .test delta --parents tests/cluster "$SRC")
  fi
}

install_packages
mkdir -p "$SCRATCH"
snapshot
write_config
trap stop_cluster EXIT
start_cluster
python "$SRC/tests/cluster/slurm_e2e.py" --src "$SRC" --repo "$REPO" --scratch "$SCRATCH" "${@:2}"  # e.g. --retrain, --skip-e2e
