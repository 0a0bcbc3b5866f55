#!/usr/bin/env bash
# A one-node SLURM cluster on this machine, for the cluster tests (tests/train/test_cluster.py) and for trying
# `python -m train.pipeline --cluster slurm --submit` without a cluster: munged, slurmctld and slurmd on
# localhost, this machine as the only node with its cores as CPUs, no accounting database.
#
#   sudo scripts/local_slurm.sh          # installs slurm-wlm and munge (Debian/Ubuntu apt) when missing
#
# Idempotent: when a controller answers and the node is up, it does nothing. Needs root (apt-get, the daemons).
# Exit 0 when the cluster is up, 1 with one line on stderr saying why when it cannot be.
set -euo pipefail

say() { echo "local_slurm: $*" >&2; }
node_up() {
    scontrol ping 2>/dev/null | grep -q "is UP" && sinfo -h -o "%T" 2>/dev/null | grep -qE "^(idle|mixed|allocated|completing)"
}

if command -v scontrol >/dev/null && node_up; then
    say "a SLURM cluster is already running here ($(sinfo -h -o '%P %D node(s) %c CPUs %T' | head -1))"
    exit 0
fi
if [ "$(id -u)" != 0 ]; then
    say "not root: starting slurmctld/slurmd needs root (run it with sudo)"
    exit 1
fi
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v munged >/dev/null; then
    if ! command -v apt-get >/dev/null; then
        say "slurm-wlm and munge are not installed and there is no apt-get to install them"
        exit 1
    fi
    say "installing slurm-wlm and munge (apt-get) ..."
    if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq slurm-wlm munge; } >/tmp/local_slurm_apt.log 2>&1; then
        say "apt-get install slurm-wlm munge failed (see /tmp/local_slurm_apt.log)"
        exit 1
    fi
fi

# munge: the key the Debian package made, or a new one; munged runs as the munge user.
install -d -o munge -g munge -m 0700 /etc/munge /var/lib/munge /var/log/munge
install -d -o munge -g munge -m 0755 /run/munge
if [ ! -s /etc/munge/munge.key ]; then
    dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
fi
chown munge:munge /etc/munge/munge.key && chmod 0400 /etc/munge/munge.key
if ! munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1; then
    runuser -u munge -- /usr/sbin/munged </dev/null >/dev/null 2>&1
    for _ in $(seq 50); do munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.2; done
fi

# slurm.conf: the node line as slurmd itself sees this machine (CPUs, cores, memory), so that it registers valid.
node_line=$(slurmd -C | head -1)
node=$(hostname -s)
mkdir -p /etc/slurm /var/spool/slurmctld /var/spool/slurmd /var/log/slurm
chown slurm:slurm /var/spool/slurmctld /var/log/slurm
cat >/etc/slurm/slurm.conf <<EOF
# Written by scripts/local_slurm.sh: a one-node cluster on localhost, no accounting.
ClusterName=localhost
SlurmctldHost=${node}(127.0.0.1)
SlurmUser=slurm
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
# Finished jobs stay visible to scontrol for 10 minutes (the watcher reads their end state and reason there).
MinJobAge=600
StateSaveLocation=/var/spool/slurmctld
SlurmdSpoolDir=/var/spool/slurmd
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
${node_line% UpTime*} NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=debug Nodes=${node} Default=YES MaxTime=INFINITE State=UP
EOF

# The daemons get no stdout/stderr of ours: a caller reading this script's output to its end would wait on them.
pgrep -x slurmctld >/dev/null || slurmctld </dev/null >/dev/null 2>&1
pgrep -x slurmd >/dev/null || slurmd </dev/null >/dev/null 2>&1
for _ in $(seq 100); do
    if node_up; then
        say "SLURM is up: $(sinfo -h -o '%P %D node(s) %c CPUs %T' | head -1)"
        exit 0
    fi
    # A node that came up DOWN (an earlier run's state) is put back into service.
    sinfo -h -o "%T" 2>/dev/null | grep -qE "^(down|drain)" && scontrol update NodeName="${node}" State=RESUME 2>/dev/null || true
    sleep 0.3
done
say "slurmctld/slurmd did not come up in 30 s (see /var/log/slurm/slurmctld.log and slurmd.log)"
exit 1
