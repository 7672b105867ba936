#!/usr/bin/env bash
# Stop the daemons that .ci/slurm-up.sh started (and only those: each one's pid is recorded in
# $CCBENCH_SLURM_DIR/started/<name>), in reverse order of their start. Configuration, the
# accounting database and installed packages stay, so the next slurm-up.sh is fast.
set -uo pipefail

STATE=${CCBENCH_SLURM_DIR:-/var/lib/ccbench-slurm}
MARK="# written by ccbench .ci/slurm-up.sh"

say() { echo "slurm-down: $*" >&2; }

alive() {  # alive PID COMM: a live (not zombie) process of that name
    [ -r "/proc/$1/comm" ] && [ "$(cat "/proc/$1/comm")" = "$2" ] \
        && ! grep -q '^State:.*Z' "/proc/$1/status"
}

stop() {  # stop NAME COMM
    local f="$STATE/started/$1" pid deadline
    [ -f "$f" ] || return 0
    pid=$(tr -d ' \n' <"$f")
    if [ -n "$pid" ] && alive "$pid" "$2"; then
        kill -TERM "$pid"
        deadline=$((SECONDS + 20))
        while alive "$pid" "$2" && [ $SECONDS -lt $deadline ]; do sleep 0.2; done
        if alive "$pid" "$2"; then
            say "$1 ($pid) ignored SIGTERM for 20 s; killing it"
            kill -KILL "$pid"
        fi
        say "stopped $1 ($pid)"
    fi
    rm -f "$f"
}

[ -d "$STATE/started" ] || { say "nothing was started from $STATE"; exit 0; }
stop slurmd slurmd
stop slurmctld slurmctld
stop slurmdbd slurmdbd
stop mariadbd mariadbd
stop munged munged
if grep -qF "$MARK" /etc/hosts 2>/dev/null; then  # the host name line slurm-up.sh added
    grep -vF "$MARK" /etc/hosts >/etc/hosts.ccbench-tmp && cat /etc/hosts.ccbench-tmp >/etc/hosts
    rm -f /etc/hosts.ccbench-tmp
fi
