#!/usr/bin/env bash
# A one-node Slurm cluster on this machine, for running the DAG through
# `snakemake --profile profiles/slurm-local` exactly as on a real cluster.
#
#   tools/slurm_local.sh start    # write slurm.conf, start munged, slurmctld, slurmd
#   tools/slurm_local.sh stop     # stop them (state and logs stay in $SLURM_LOCAL_STATE)
#   tools/slurm_local.sh status
#
# Needs Debian's packages (as root): apt-get install -y slurmd slurmctld slurm-client munge
# The node is this host with every CPU and the memory `free` reports; partitions
# `cpu` and `gpu` both point at it (no GPUs are declared: the `gpu` partition only
# lets profiles written for a real cluster submit unchanged). No cgroups: process
# tracking by /proc, no task confinement. No accounting daemon: job states come
# from `squeue`, which keeps finished jobs for MinJobAge seconds.
set -euo pipefail

STATE=${SLURM_LOCAL_STATE:-/var/lib/orbis2-slurm}
CONF=/etc/slurm/slurm.conf
HOST=$(hostname -s)

die() { echo "slurm_local.sh: $*" >&2; exit 2; }

write_conf() {
    local cpus mem
    cpus=$(nproc --all)
    mem=$(free -m | awk '/^Mem:/ {print int($2 * 0.9)}')
    mkdir -p "$STATE/ctld" "$STATE/d" /etc/slurm
    cat > "$CONF" <<EOF
# Written by tools/slurm_local.sh: a one-node cluster on $HOST.
ClusterName=orbis2-local
SlurmctldHost=$HOST
SlurmUser=root
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
MinJobAge=3600
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/slurmctld.log
SlurmdLogFile=$STATE/slurmd.log
NodeName=$HOST CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=cpu Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
PartitionName=gpu Nodes=$HOST MaxTime=INFINITE State=UP
EOF
}

start_munge() {
    [[ -s /etc/munge/munge.key ]] || { mungekey --create 2>/dev/null || create-munge-key -f; }
    chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge
    if ! munge -n >/dev/null 2>&1; then
        runuser -u munge -- /usr/sbin/munged
        sleep 1
        munge -n | unmunge >/dev/null || die "munged did not start (see /var/log/munge/munged.log)"
    fi
}

stop_pid() {  # stop the daemon whose pid file is $1
    [[ -f $1 ]] || return 0
    local pid
    pid=$(cat "$1")
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 20); do kill -0 "$pid" 2>/dev/null || break; sleep 0.5; done
    rm -f "$1"
}

case ${1:-} in
start)
    [[ $(id -u) == 0 ]] || die "run as root (it writes $CONF and starts daemons)"
    command -v slurmctld >/dev/null || die "Slurm is not installed: apt-get install -y slurmd slurmctld slurm-client munge"
    write_conf
    start_munge
    [[ -f $STATE/slurmctld.pid ]] && kill -0 "$(cat "$STATE/slurmctld.pid")" 2>/dev/null || slurmctld
    [[ -f $STATE/slurmd.pid ]] && kill -0 "$(cat "$STATE/slurmd.pid")" 2>/dev/null || slurmd
    for _ in $(seq 30); do
        sinfo -h -o %t 2>/dev/null | grep -qE '^(idle|mix|alloc)' && break
        sleep 1
    done
    scontrol update NodeName="$HOST" State=RESUME 2>/dev/null || true
    sinfo
    ;;
stop)
    stop_pid "$STATE/slurmd.pid"
    stop_pid "$STATE/slurmctld.pid"
    echo "slurmctld and slurmd stopped (munged left running; state in $STATE)"
    ;;
status)
    sinfo && squeue
    ;;
*)
    die "usage: $0 start|stop|status"
    ;;
esac
