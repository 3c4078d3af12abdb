#!/usr/bin/env bash
# Start a Ray head node on this machine for `ray job submit`: bound to 127.0.0.1 by default, token
# authentication on. It runs in its own process group so that cluster/stop-head.sh stops exactly it.
#
#   cluster/start-head.sh [extra `ray start` flags, e.g. --num-cpus=8]
#   export RAY_ADDRESS=http://127.0.0.1:8265          # printed below; the Jobs API of this head
#   ray job submit --runtime-env cluster/runtime_env.yaml --working-dir . -- \
#       python pipelines/generate.py --maps train --num-maps 20 --out /abs/path/data/train
#   cluster/stop-head.sh
#
# Settings (environment): RAY_HEAD_IP (127.0.0.1; set the machine's address to let worker nodes join),
# RAY_PORT (6379), RAY_DASHBOARD_PORT (8265), RAY_CLIENT_PORT (10001), RAY_HEAD_DIR (/tmp/roken-ray: logs,
# pid, Ray's temp files), PYTHON (python: the environment jobs run in), RAY_AUTH_TOKEN or
# RAY_AUTH_TOKEN_PATH (default ~/.ray/auth_token, generated with mode 600 when missing).
set -euo pipefail

PY=${PYTHON:-python}
PYBIN=$(dirname "$("$PY" -c 'import sys; print(sys.executable)')")
# A submitted job runs `python` from the head's PATH: make that this environment's python.
export PATH="$PYBIN:$PATH"
export RAY_AUTH_MODE=token
if [ -z "${RAY_AUTH_TOKEN:-}" ]; then
    TOKEN_FILE=${RAY_AUTH_TOKEN_PATH:-$HOME/.ray/auth_token}
    if [ ! -s "$TOKEN_FILE" ]; then
        mkdir -p "$(dirname "$TOKEN_FILE")"
        (umask 077 && "$PY" -c 'import secrets; print(secrets.token_hex(32))' > "$TOKEN_FILE")
        echo "generated an auth token in $TOKEN_FILE (copy it to every client and worker node)"
    fi
    export RAY_AUTH_TOKEN_PATH=$TOKEN_FILE
fi

HEAD_IP=${RAY_HEAD_IP:-127.0.0.1}
PORT=${RAY_PORT:-6379}
DASH_PORT=${RAY_DASHBOARD_PORT:-8265}
CLIENT_PORT=${RAY_CLIENT_PORT:-10001}
HEAD_DIR=${RAY_HEAD_DIR:-/tmp/roken-ray}
mkdir -p "$HEAD_DIR"
running() {  # is process $1 alive? (a zombie left for a parent that never reaps it does not count)
    [ -n "$(ps -o stat= -p "$1" 2>/dev/null | grep -v '^Z')" ]
}
if [ -f "$HEAD_DIR/head.pid" ] && running "$(cat "$HEAD_DIR/head.pid")"; then
    echo "a head started from $HEAD_DIR is already running (pid $(cat "$HEAD_DIR/head.pid")); stop it with" \
         "RAY_HEAD_DIR=$HEAD_DIR cluster/stop-head.sh" >&2
    exit 1
fi

# --block keeps `ray start` in the foreground of its own session, so every process of this head shares
# one process group (the pid below) and stop-head.sh can stop them all without touching other clusters.
setsid "$PYBIN/ray" start --head --block \
    --node-ip-address="$HEAD_IP" --port="$PORT" \
    --dashboard-host=127.0.0.1 --dashboard-port="$DASH_PORT" \
    --ray-client-server-port="$CLIENT_PORT" \
    --temp-dir="$HEAD_DIR/tmp" --disable-usage-stats "$@" > "$HEAD_DIR/head.log" 2>&1 &
echo $! > "$HEAD_DIR/head.pid"

for _ in $(seq 1 120); do
    if "$PYBIN/ray" job list --address "http://127.0.0.1:$DASH_PORT" > /dev/null 2>&1; then
        echo "Ray head up: GCS $HEAD_IP:$PORT, Jobs API http://127.0.0.1:$DASH_PORT (pid $(cat "$HEAD_DIR/head.pid"), log $HEAD_DIR/head.log)"
        echo "  export RAY_AUTH_MODE=token RAY_ADDRESS=http://127.0.0.1:$DASH_PORT"
        exit 0
    fi
    if ! running "$(cat "$HEAD_DIR/head.pid")"; then
        echo "the Ray head exited; its log ($HEAD_DIR/head.log) ends with:" >&2
        tail -n 20 "$HEAD_DIR/head.log" >&2
        exit 1
    fi
    sleep 0.5
done
echo "the Ray head did not answer within 60 s; see $HEAD_DIR/head.log" >&2
exit 1
