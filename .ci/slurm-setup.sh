#!/usr/bin/env bash
# A single-node SLURM cluster on this machine, for tests/test_slurm.py (CI only).
#
#   bash .ci/slurm-setup.sh          install (Debian: slurm-wlm + munge), configure, start
#
# Controller and compute node are this host; partitions "cpu" (default) and "gpu" (same node,
# no GPUs) match workflow/profiles/slurm. Needs root and a Debian-like system with apt-get;
# no systemd: munged, slurmctld and slurmd are started as plain daemons. No accounting
# database: `sacct` does not work, so the pipeline's jobs are tracked with
# `--slurm-status-command squeue` (MinJobAge keeps finished jobs visible to squeue for
# 10 minutes) and every finished job is logged to $JOBCOMP_LOG.
# Idempotent: a second run leaves a working cluster alone; it rewrites the configuration and
# restarts the daemons only when the configuration changed or a daemon is not answering.
# Exits non-zero with a message saying what failed.
set -euo pipefail

CONF_DIR=/etc/slurm
CONF=$CONF_DIR/slurm.conf
MARKER="# written by .ci/slurm-setup.sh"
LOG_DIR=/var/log/slurm
STATE_DIR=/var/lib/slurm
JOBCOMP_LOG=$LOG_DIR/jobcomp.log
NODE=$(hostname -s)

die() { echo "slurm-setup: ERROR: $*" >&2; exit 1; }
say() { echo "slurm-setup: $*"; }

[ "$(id -u)" -eq 0 ] || die "must run as root (it installs packages and starts daemons)"

# --- packages ---------------------------------------------------------------------------------
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null \
        || ! command -v sinfo >/dev/null || ! command -v munged >/dev/null; then
    command -v apt-get >/dev/null || die "slurm is not installed and apt-get is not available"
    say "installing slurm-wlm and munge with apt-get"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq || die "apt-get update failed"
    apt-get install -y -qq --no-install-recommends slurm-wlm munge >/dev/null \
        || die "apt-get install slurm-wlm munge failed"
fi
say "$(slurmctld -V)"

# --- munge ------------------------------------------------------------------------------------
install -d -o munge -g munge -m 0700 /etc/munge /var/lib/munge /var/log/munge
install -d -o munge -g munge -m 0755 /run/munge
if [ ! -s /etc/munge/munge.key ]; then
    say "creating /etc/munge/munge.key"
    if command -v mungekey >/dev/null; then
        mungekey --create --keyfile=/etc/munge/munge.key --force
    else
        dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 status=none
    fi
fi
chown munge:munge /etc/munge/munge.key
chmod 0400 /etc/munge/munge.key
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    say "starting munged"
    rm -f /run/munge/munged.pid
    runuser -u munge -- munged --force || die "munged did not start (see /var/log/munge/munged.log)"
    for _ in $(seq 20); do
        munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break
        sleep 0.5
    done
    munge -n | unmunge >/dev/null || die "munge credentials do not work (see /var/log/munge/munged.log)"
fi

# --- slurm.conf ---------------------------------------------------------------------------------
# The node's hardware as slurmd sees it; memory with 10% headroom so that small fluctuations of
# what the kernel reports never drain the node ("Low RealMemory").
read -r CPUS BOARDS SOCKETS CORES THREADS MEM < <(slurmd -C | head -1 | tr ' ' '\n' | awk -F= '
    $1=="CPUs"{c=$2} $1=="Boards"{b=$2} $1=="SocketsPerBoard"{s=$2}
    $1=="CoresPerSocket"{k=$2} $1=="ThreadsPerCore"{t=$2} $1=="RealMemory"{m=$2}
    END{print c, b, s, k, t, m}')
[ -n "${CPUS:-}" ] && [ -n "${MEM:-}" ] || die "'slurmd -C' did not report CPUs and RealMemory"
MEM=$((MEM * 9 / 10))

NEW_CONF=$(cat <<EOF
$MARKER: single-node test cluster, do not use in production
ClusterName=localci
SlurmctldHost=$NODE(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CryptoType=crypto/munge
MpiDefault=none
StateSaveLocation=$STATE_DIR/slurmctld
SlurmdSpoolDir=$STATE_DIR/slurmd
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=$LOG_DIR/slurmctld.log
SlurmdLogFile=$LOG_DIR/slurmd.log
# No cgroups in containers / sandboxes.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
# No slurmdbd: no sacct. Finished jobs stay in squeue for MinJobAge seconds and are logged here.
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc=$JOBCOMP_LOG
MinJobAge=600
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
SlurmdTimeout=60
InactiveLimit=0
KillWait=10
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$CPUS Boards=$BOARDS SocketsPerBoard=$SOCKETS CoresPerSocket=$CORES ThreadsPerCore=$THREADS RealMemory=$MEM State=UNKNOWN
PartitionName=cpu Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
PartitionName=gpu Nodes=$NODE Default=NO MaxTime=INFINITE State=UP
EOF
)

if [ -f "$CONF" ] && ! grep -qF "$MARKER" "$CONF"; then
    die "$CONF exists and was not written by this script; move it away to let it configure SLURM"
fi
install -d -m 0755 "$CONF_DIR" "$LOG_DIR" "$STATE_DIR/slurmctld" "$STATE_DIR/slurmd"
[ -f "$CONF_DIR/cgroup.conf" ] || echo "# unused: no cgroup plugins configured" > "$CONF_DIR/cgroup.conf"

daemon_alive() {  # pidfile -> true when that process runs
    [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null
}
stop_daemon() {   # pidfile
    if daemon_alive "$1"; then
        local pid; pid=$(cat "$1")
        kill "$pid"
        for _ in $(seq 40); do kill -0 "$pid" 2>/dev/null || break; sleep 0.25; done
        kill -0 "$pid" 2>/dev/null && kill -9 "$pid"
    fi
    rm -f "$1"
}

RESTART=0
if [ ! -f "$CONF" ] || [ "$(cat "$CONF")" != "$NEW_CONF" ]; then
    say "writing $CONF"
    printf '%s\n' "$NEW_CONF" > "$CONF"
    RESTART=1
fi
if [ "$RESTART" = 1 ] || ! daemon_alive /run/slurmctld.pid || ! daemon_alive /run/slurmd.pid \
        || ! timeout 20 scontrol ping 2>/dev/null | grep -q "is UP"; then
    say "(re)starting slurmctld and slurmd"
    stop_daemon /run/slurmd.pid
    stop_daemon /run/slurmctld.pid
    slurmctld || die "slurmctld did not start (see $LOG_DIR/slurmctld.log)"
    for _ in $(seq 40); do
        timeout 5 scontrol ping 2>/dev/null | grep -q "is UP" && break
        sleep 0.5
    done
    timeout 5 scontrol ping | grep -q "is UP" \
        || die "slurmctld does not answer (see $LOG_DIR/slurmctld.log)"
    slurmd -N "$NODE" || die "slurmd did not start (see $LOG_DIR/slurmd.log)"
fi

# --- wait for the node, then run one job through each partition --------------------------------
state=""
for _ in $(seq 60); do
    state=$(sinfo -h -N -n "$NODE" -o %T 2>/dev/null | head -1)
    case "$state" in
        idle|mixed|allocated|completing) break ;;
        down*|drain*|fail*) scontrol update NodeName="$NODE" State=RESUME 2>/dev/null || true ;;
    esac
    sleep 1
done
case "$state" in
    idle|mixed|allocated|completing) ;;
    *) die "node $NODE is '$state', not idle (see $LOG_DIR/slurmd.log, 'scontrol show node')" ;;
esac

for partition in cpu gpu; do
    out=$(timeout 120 srun --partition "$partition" --ntasks 1 --mem 10 --time 1 \
          --job-name slurm-setup-check hostname 2>&1) \
        || die "a test job on partition '$partition' failed: $out"
done
say "cluster ready: $(sinfo -h -o '%P %a %D %T' | tr '\n' ';')"
