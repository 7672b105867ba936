#!/usr/bin/env bash
# Bring up a one-node SLURM with accounting (slurmdbd + a private MariaDB) on a Debian machine
# where we are root and there is no systemd: what the `slurm` tests and `ccdata generate
# --launcher slurm` need. Idempotent: a second run checks the daemons and returns in seconds.
#
#   .ci/slurm-up.sh      # then: sinfo, sbatch, sacct work; .ci/slurm-down.sh stops it again
#
# Everything it creates lives under $CCBENCH_SLURM_DIR (default /var/lib/ccbench-slurm: state,
# logs, pid files, the MariaDB data directory), except what SLURM and munge read from fixed
# places: /etc/slurm/{slurm,slurmdbd}.conf, /etc/munge/munge.key, /run/munge, and a line in
# /etc/hosts when the hostname does not resolve. It refuses to overwrite a slurm.conf it did
# not write. Each daemon it starts is recorded in $CCBENCH_SLURM_DIR/started/<name> (its pid),
# so that slurm-down.sh stops only those.
set -euo pipefail

STATE=${CCBENCH_SLURM_DIR:-/var/lib/ccbench-slurm}
CLUSTER=ccbench
DB_PORT=${CCBENCH_SLURM_DB_PORT:-3399}  # the private MariaDB, on 127.0.0.1 only
MARK="# written by ccbench .ci/slurm-up.sh"
PACKAGES=(munge slurmctld slurmd slurm-client slurmdbd mariadb-server)

say() { echo "slurm-up: $*" >&2; }
die() { say "error: $*"; exit 1; }

[ "$(id -u)" = 0 ] || die "needs root (it installs packages and starts system daemons)"
command -v dpkg-query >/dev/null || die "not a Debian machine (no dpkg-query)"

# ── Packages ────────────────────────────────────────────────────────────────────────────────
missing=()
for p in "${PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    command -v apt-get >/dev/null || die "missing packages ${missing[*]} and no apt-get"
    say "installing ${missing[*]}"
    # Keep the packages' init scripts from starting daemons: we start our own instances.
    policy=/usr/sbin/policy-rc.d
    if [ ! -e $policy ]; then
        printf '#!/bin/sh\nexit 101\n' >$policy && chmod 755 $policy
        trap 'rm -f /usr/sbin/policy-rc.d' EXIT
    fi
    apt_install() {
        DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends \
            "${missing[@]}" >"$1" 2>&1
    }
    log=$(mktemp)
    if ! apt_install "$log"; then  # stale or absent package lists
        apt-get update -q >/dev/null 2>&1 || true
        apt_install "$log" || { tail -n 20 "$log" >&2; die "apt-get install failed"; }
    fi
    rm -f "$log"
fi

HOST=$(hostname -s)
mkdir -p "$STATE"/{started,run,log}
getent passwd slurm >/dev/null || useradd --system --no-create-home --shell /usr/sbin/nologin slurm
chown slurm:slurm "$STATE/run" "$STATE/log"

# ── Helpers ─────────────────────────────────────────────────────────────────────────────────
alive() {  # alive PID COMM: a live process of that name (a zombie is dead: where pid 1 does
    # not reap orphans, stopped daemons stay zombies)
    [ -n "$1" ] && [ -r "/proc/$1/comm" ] && [ "$(cat "/proc/$1/comm")" = "$2" ] \
        && ! grep -q '^State:.*Z' "/proc/$1/status"
}
pid_alive() {  # pid_alive PIDFILE COMM: the pid file names a live process of that name
    [ -s "$1" ] && alive "$(tr -d ' \n' <"$1")" "$2"
}
gone() { ! pid_alive "$1" "$2"; }
wait_for() {  # wait_for SECONDS COMMAND...: poll until COMMAND succeeds
    local deadline=$((SECONDS + $1))
    shift
    until "$@" >/dev/null 2>&1; do
        [ $SECONDS -lt $deadline ] || return 1
        sleep 0.2
    done
}
record_start() {  # record_start NAME PIDFILE COMM: remember that we started this daemon
    wait_for 30 pid_alive "$2" "$3" || { say "$1 did not start"; return 1; }
    cp "$2" "$STATE/started/$1"
}
write_if_changed() {  # write_if_changed FILE MODE OWNER < content; returns 0 when it changed
    local tmp
    tmp=$(mktemp "$1.XXXXXX")
    cat >"$tmp"
    chmod "$2" "$tmp" && chown "$3" "$tmp"
    if [ -f "$1" ] && cmp -s "$tmp" "$1"; then
        rm -f "$tmp"
        return 1
    fi
    mv "$tmp" "$1"
}
stop_ours() {  # stop_ours NAME COMM: stop a daemon we started (after its config changed)
    local f="$STATE/started/$1"
    if [ -f "$f" ] && pid_alive "$f" "$2"; then
        say "restarting $1 (its configuration changed)"
        kill "$(cat "$f")"
        wait_for 30 gone "$f" "$2" || kill -9 "$(cat "$f")" || true
    fi
    rm -f "$f"
}

# ── Host name ───────────────────────────────────────────────────────────────────────────────
if ! getent hosts "$HOST" >/dev/null; then
    say "adding $HOST to /etc/hosts"
    echo "127.0.1.1 $HOST $MARK" >>/etc/hosts
fi

# ── munge ───────────────────────────────────────────────────────────────────────────────────
munge_ok() { munge -n </dev/null | unmunge >/dev/null; }
if ! munge_ok 2>/dev/null; then
    mkdir -p /etc/munge /run/munge /var/lib/munge /var/log/munge
    if [ ! -s /etc/munge/munge.key ]; then
        mungekey --create --keyfile=/etc/munge/munge.key
    fi
    chown munge:munge /etc/munge/munge.key /run/munge /var/lib/munge /var/log/munge
    chmod 400 /etc/munge/munge.key
    chmod 755 /run/munge
    runuser -u munge -- munged --pid-file=/run/munge/munged.pid
    record_start munged /run/munge/munged.pid munged
    wait_for 10 munge_ok || die "munged does not answer"
fi

# ── MariaDB (a private instance for slurmdbd) ───────────────────────────────────────────────
DB_DIR=$STATE/mysql
DB_RUN=$STATE/mysql-run
DB_SOCK=$DB_RUN/mysqld.sock
sql() { mariadb --no-defaults --protocol=socket --socket="$DB_SOCK" -uroot "$@"; }
if ! pid_alive "$DB_RUN/mysqld.pid" mariadbd; then
    mkdir -p "$DB_RUN"
    chown mysql:mysql "$DB_RUN"
    if [ ! -d "$DB_DIR/mysql" ]; then
        say "initialising MariaDB in $DB_DIR"
        rm -rf "$DB_DIR"
        mariadb-install-db --no-defaults --user=mysql --datadir="$DB_DIR" \
            --auth-root-authentication-method=socket >"$STATE/log/mariadb-install.log" 2>&1 \
            || { tail -n 20 "$STATE/log/mariadb-install.log" >&2; die "mariadb-install-db failed"; }
    fi
    # setsid + nohup: the server must outlive this script and any CI step that runs it.
    setsid nohup mariadbd --no-defaults --user=mysql --datadir="$DB_DIR" \
        --socket="$DB_SOCK" --pid-file="$DB_RUN/mysqld.pid" --bind-address=127.0.0.1 \
        --port="$DB_PORT" --log-error="$STATE/log/mariadb.log" --innodb-buffer-pool-size=64M \
        </dev/null >/dev/null 2>&1 &
    record_start mariadbd "$DB_RUN/mysqld.pid" mariadbd \
        || { tail -n 20 "$STATE/log/mariadb.log" >&2; exit 1; }
    wait_for 30 sql -e "SELECT 1" || die "MariaDB does not answer on $DB_SOCK"
fi
if [ ! -s "$STATE/db-password" ]; then
    (umask 077; head -c 24 /dev/urandom | base64 | tr -d '/+=' >"$STATE/db-password")
fi
DB_PASS=$(cat "$STATE/db-password")
sql <<SQL
CREATE DATABASE IF NOT EXISTS slurm_acct_db;
CREATE USER IF NOT EXISTS 'slurm'@'127.0.0.1' IDENTIFIED BY '$DB_PASS';
ALTER USER 'slurm'@'127.0.0.1' IDENTIFIED BY '$DB_PASS';
GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';
SQL

# ── Configuration ───────────────────────────────────────────────────────────────────────────
mkdir -p /etc/slurm "$STATE/slurmctld" "$STATE/slurmd"
chown slurm:slurm "$STATE/slurmctld"
for f in /etc/slurm/slurm.conf /etc/slurm/slurmdbd.conf; do
    if [ -s "$f" ] && ! head -n 1 "$f" | grep -qF "$MARK"; then
        die "$f exists and was not written by this script; not touching a real SLURM setup"
    fi
done
# The node as slurmd sees it (first line: NodeName=... CPUs=... RealMemory=...), so that the
# configuration never claims more than the machine has.
NODE_LINE=$(slurmd -C | head -n 1)

dbd_changed=0
write_if_changed /etc/slurm/slurmdbd.conf 600 slurm:slurm <<EOF && dbd_changed=1 || true
$MARK (state in $STATE)
AuthType=auth/munge
DbdHost=localhost
SlurmUser=slurm
PidFile=$STATE/run/slurmdbd.pid
LogFile=$STATE/log/slurmdbd.log
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort=$DB_PORT
StorageUser=slurm
StoragePass=$DB_PASS
StorageLoc=slurm_acct_db
EOF

conf_changed=0
write_if_changed /etc/slurm/slurm.conf 644 root:root <<EOF && conf_changed=1 || true
$MARK (state in $STATE)
ClusterName=$CLUSTER
SlurmctldHost=$HOST
SlurmUser=slurm
SlurmdUser=root
AuthType=auth/munge
AuthInfo=cred_expire=10
CredType=cred/munge
MpiDefault=none
# No cgroups here: track processes through /proc, bind no tasks.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
# A requeued (preempted) job becomes eligible cred_expire + 1 s after its requeue, and only a
# periodic scheduling pass starts it then (by default every 60 s, backfill every 30 s).
SchedulerParameters=sched_interval=2,bf_interval=2
ReturnToService=2
KillWait=5
StateSaveLocation=$STATE/slurmctld
SlurmdSpoolDir=$STATE/slurmd
SlurmctldPidFile=$STATE/run/slurmctld.pid
SlurmdPidFile=$STATE/run/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=localhost
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
# Preemption tests: a job in "high" requeues a running job in "low" (USR2 first, 15 s grace).
PreemptType=preempt/partition_prio
PreemptMode=REQUEUE
SlurmctldParameters=preempt_send_user_signal
$NODE_LINE State=UNKNOWN
PartitionName=low Nodes=ALL Default=YES MaxTime=INFINITE State=UP PriorityTier=1 PreemptMode=REQUEUE GraceTime=15
PartitionName=high Nodes=ALL MaxTime=INFINITE State=UP PriorityTier=10 PreemptMode=OFF
EOF

# ── Daemons ─────────────────────────────────────────────────────────────────────────────────
if [ $dbd_changed = 1 ]; then stop_ours slurmdbd slurmdbd; fi
if [ $conf_changed = 1 ]; then stop_ours slurmd slurmd; stop_ours slurmctld slurmctld; fi

if ! pid_alive "$STATE/run/slurmdbd.pid" slurmdbd; then
    slurmdbd
    record_start slurmdbd "$STATE/run/slurmdbd.pid" slurmdbd \
        || { tail -n 20 "$STATE/log/slurmdbd.log" >&2; exit 1; }
fi
cluster_known() { sacctmgr -n -P show cluster "$CLUSTER" format=cluster | grep -qx "$CLUSTER"; }
wait_for 30 sacctmgr -n show cluster \
    || { tail -n 20 "$STATE/log/slurmdbd.log" >&2; die "slurmdbd does not answer"; }
cluster_known || sacctmgr -i add cluster "$CLUSTER" >/dev/null

if ! pid_alive "$STATE/run/slurmctld.pid" slurmctld; then
    slurmctld
    record_start slurmctld "$STATE/run/slurmctld.pid" slurmctld \
        || { tail -n 20 "$STATE/log/slurmctld.log" >&2; exit 1; }
fi
if ! pid_alive "$STATE/run/slurmd.pid" slurmd; then
    slurmd
    record_start slurmd "$STATE/run/slurmd.pid" slurmd \
        || { tail -n 20 "$STATE/log/slurmd.log" >&2; exit 1; }
fi

# idle on a fresh start; mix or alloc when jobs already run on a node that was up
node_up() { [[ "$(sinfo -h -N -n "$HOST" -o %t | sort -u)" =~ ^(idle|mix|alloc)$ ]]; }
sacct_ok() { sacct -n -X -S now-1minutes -o JobID; }
if ! wait_for 60 node_up; then
    sinfo -N -l >&2 || true
    tail -n 20 "$STATE/log/slurmctld.log" "$STATE/log/slurmd.log" >&2
    die "node $HOST did not come up (idle)"
fi
wait_for 30 sacct_ok || die "sacct does not answer"
say "up: node $HOST idle, partitions low (default) and high, accounting on (state in $STATE)"
