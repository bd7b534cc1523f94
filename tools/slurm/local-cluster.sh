#!/usr/bin/env bash
# A one-node Slurm on this machine, as root and without systemd, for `warpsense study run --executor slurm` and the
# `slurm`-marked tests: munged as the munge user, slurmctld and slurmd as root, the node's CPUs and memory (as
# `slurmd -C` reads them) in one partition, no accounting database (squeue serves the job states).
#
#   bash tools/slurm/local-cluster.sh start    # installs slurm-wlm and munge (apt-get) if missing; fast if running
#   bash tools/slurm/local-cluster.sh status   # the controller, the node, the queue
#   bash tools/slurm/local-cluster.sh stop
#
# It writes /etc/slurm/slurm.conf (the path Slurm's commands read) only where none exists or where it wrote the one
# there; state, spool and logs go to /var/lib/warpsense-slurm. Exits non-zero where Slurm cannot start.
set -euo pipefail

CONF=/etc/slurm/slurm.conf
STATE=/var/lib/warpsense-slurm
MARK="# written by warpsense tools/slurm/local-cluster.sh"
PARTITION=debug
MUNGE_PID=/run/munge/munged.pid

say() { echo "local-cluster: $*"; }
fail() { echo "local-cluster: error: $*" >&2; exit 1; }

controller_up() { command -v scontrol >/dev/null && timeout 10 scontrol ping 2>/dev/null | grep -q "is UP"; }

node_state() { timeout 10 sinfo -h -N -o "%T" 2>/dev/null | head -n 1; }

ready() {  # the controller answers and the node takes jobs
    controller_up || return 1
    case "$(node_state)" in idle* | mixed* | allocated* | completing*) return 0 ;; *) return 1 ;; esac
}

pid_alive() { [[ -f "$1" ]] && kill -0 "$(cat "$1")" 2>/dev/null; }

install_packages() {
    if command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v munged >/dev/null; then
        return
    fi
    say "installing slurm-wlm and munge (apt-get)"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null
    apt-get install -y -qq slurm-wlm munge >/dev/null
}

write_config() {  # returns 1 where the file was already so
    if [[ -f "$CONF" ]] && ! grep -qF "$MARK" "$CONF"; then
        fail "$CONF exists and was not written by this script: not touching it (is this machine on a real cluster?)"
    fi
    local host node
    host=$(hostname -s)
    # the node as slurmd sees it: NodeName=<host> CPUs=... Boards=... SocketsPerBoard=... RealMemory=...
    node=$(slurmd -C | head -n 1)
    [[ "$node" == NodeName=* ]] || fail "slurmd -C did not describe this node: $node"
    mkdir -p "$(dirname "$CONF")" "$STATE/ctld" "$STATE/d"
    cat >"$CONF.new" <<EOF
$MARK
ClusterName=warpsense-local
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
# a requeued job (a preempted task) waits cred_expire seconds before it starts again (default 120)
AuthInfo=cred_expire=5
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/slurmctld.log
SlurmdLogFile=$STATE/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
MpiDefault=none
ReturnToService=2
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
# scancel's SIGKILL follows its SIGTERM (which submitit's tasks ignore: they wait for USR2) after KillWait seconds
KillWait=1
MinJobAge=300
SchedulerParameters=bf_interval=1
$node NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=$PARTITION Nodes=ALL Default=YES MaxTime=INFINITE State=UP
EOF
    if cmp -s "$CONF.new" "$CONF"; then
        rm -f "$CONF.new"
        return 1
    fi
    mv "$CONF.new" "$CONF"
    say "wrote $CONF"
}

start_munge() {
    if munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
        return
    fi
    if [[ ! -s /etc/munge/munge.key ]]; then
        mungekey --create --keyfile=/etc/munge/munge.key
    fi
    chown munge:munge /etc/munge/munge.key
    chmod 400 /etc/munge/munge.key
    install -d -o munge -g munge -m 0755 /run/munge
    install -d -o munge -g munge -m 0700 /var/log/munge /var/lib/munge
    runuser -u munge -- munged --force
    for _ in $(seq 50); do
        munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && return
        sleep 0.1
    done
    fail "munged did not start (log: /var/log/munge/munged.log)"
}

start() {
    [[ $(id -u) == 0 ]] || fail "run as root (it installs packages and starts daemons)"
    if ready; then
        if write_config; then
            scontrol reconfigure
            say "running; configuration reloaded"
        else
            say "already running"
        fi
        status
        return
    fi
    install_packages
    write_config || true
    start_munge
    pid_alive "$STATE/slurmctld.pid" || slurmctld
    pid_alive "$STATE/slurmd.pid" || slurmd
    local state=""
    for _ in $(seq 60); do
        if controller_up; then
            state=$(node_state)
            case "$state" in
                idle* | mixed* | allocated*) break ;;
                down* | drain*) scontrol update nodename="$(hostname -s)" state=resume 2>/dev/null || true ;;
            esac
        fi
        sleep 0.5
    done
    ready || fail "the node did not come up (state: ${state:-no answer}); logs: $STATE/slurmctld.log, $STATE/slurmd.log"
    status
}

stop() {
    if controller_up; then
        scontrol shutdown >/dev/null || true  # slurmctld and the slurmd
    fi
    for pidfile in "$STATE/slurmctld.pid" "$STATE/slurmd.pid"; do
        for _ in $(seq 50); do pid_alive "$pidfile" || break; sleep 0.1; done
        if pid_alive "$pidfile"; then kill "$(cat "$pidfile")"; fi
    done
    if pid_alive "$MUNGE_PID"; then munged --stop >/dev/null 2>&1 || kill "$(cat "$MUNGE_PID")"; fi
    say "stopped"
}

status() {
    if ! controller_up; then
        say "not running"
        return 3
    fi
    sinfo -o "%P %a %l %D %T %C %m" 2>/dev/null
    squeue 2>/dev/null
}

case "${1:-}" in
    start) start ;;
    stop) stop ;;
    status) status ;;
    *) echo "usage: $0 start|stop|status" >&2; exit 2 ;;
esac
