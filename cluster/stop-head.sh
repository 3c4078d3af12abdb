#!/usr/bin/env bash
# Stop the Ray head that cluster/start-head.sh started from RAY_HEAD_DIR (default /tmp/roken-ray): its
# process group only, never other Ray clusters on the machine (unlike `ray stop`).
set -euo pipefail
HEAD_DIR=${RAY_HEAD_DIR:-/tmp/roken-ray}
PID_FILE="$HEAD_DIR/head.pid"
if [ ! -f "$PID_FILE" ]; then
    echo "no head pid file at $PID_FILE; nothing to stop" >&2
    exit 0
fi
PGID=$(cat "$PID_FILE")
alive() {  # processes of the group that still run (zombies waiting for their parent do not count)
    ps -eo pgid=,stat= | awk -v g="$PGID" '$1 == g && $2 !~ /^Z/ {n++} END {exit n == 0}'
}
# SIGTERM to `ray start --block` drains the node and stops its processes in order (a few seconds; signalling
# the whole group at once makes them wait on each other instead). Whatever is left after RAY_STOP_GRACE
# seconds (default 40) is killed.
GRACE=${RAY_STOP_GRACE:-40}
kill -TERM "$PGID" 2>/dev/null || true
for _ in $(seq 1 $((GRACE * 2))); do
    if ! alive; then
        rm -f "$PID_FILE"
        echo "stopped the Ray head (process group $PGID)"
        exit 0
    fi
    sleep 0.5
done
kill -KILL -- "-$PGID" 2>/dev/null || true
rm -f "$PID_FILE"
echo "stopped the Ray head (process group $PGID): killed after ${GRACE} s"
