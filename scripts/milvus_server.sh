#!/usr/bin/env bash
# A Milvus standalone server for development and CI (docs/milvus.md): PyPI `milvus==2.3.5` ships
# the Milvus 2.3.5 binary (embedded etcd, rocksmq, local storage). It goes in its own venv so it
# never touches the project's pymilvus / milvus-lite.
#   scripts/milvus_server.sh start    install if needed, start, wait until healthy (or fail)
#   scripts/milvus_server.sh stop     stop the server this script started (by its pid file)
#   scripts/milvus_server.sh status   exit 0 when a server answers the health check
# Settings (environment):
#   MILVUS_VENV=.venv-milvus      the server's venv (created on first start)
#   MILVUS_DATA=.milvus-data      its data; the first start unpacks ~400 MB into DATA/bin
#   MILVUS_START_TIMEOUT=180      seconds to wait for the health check
#   MILVUS_PORT_SHIFT=0           added to every port: a second server beside the first needs
#                                 its own ports and MILVUS_DATA (e.g. 100: client 19630)
#   MILVUS_AUTH=0                 1: authorization on (user root, password Milvus)
#   MILVUS_HEALTH                 the health check (default from the shift)
# Client URI: http://127.0.0.1:19530 (+ shift); health: http://127.0.0.1:9091/healthz (+ shift).
# Every port is bound exactly (scripts/milvus_launch.py): a start right after a kill -9 keeps
# its ports instead of moving to the next free ones.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${MILVUS_VENV:-.venv-milvus}
DATA=${MILVUS_DATA:-.milvus-data}
TIMEOUT=${MILVUS_START_TIMEOUT:-180}
SHIFT=${MILVUS_PORT_SHIFT:-0}
HEALTH_PORT=$((9091 + SHIFT))
HEALTH=${MILVUS_HEALTH:-http://127.0.0.1:$HEALTH_PORT/healthz}
PIDFILE="$DATA/server.pid"

healthy() { [ "$(curl -s -m 2 "$HEALTH" 2>/dev/null)" = "OK" ]; }

stop() {
    [ -f "$PIDFILE" ] || { echo "milvus: no $PIDFILE: nothing this script started"; return 0; }
    pid=$(cat "$PIDFILE")
    # the wrapper leads its own process group (setsid): -9 to the group ends the binary and the
    # wrapper together (SIGTERM would wait for a graceful stop; the data is flushed per insert)
    kill -9 -- "-$pid" 2>/dev/null || true
    # until no process of the group is left (its ports are free for the next start)
    for _ in $(seq 100); do kill -0 -- "-$pid" 2>/dev/null || break; sleep 0.1; done
    rm -f "$PIDFILE"
    echo "milvus: stopped (process group $pid)"
}

start() {
    if healthy; then
        echo "milvus: a server already answers at $HEALTH; using it"
        return 0
    fi
    if [ ! -x "$VENV/bin/milvus-server" ]; then
        echo "milvus: installing milvus==2.3.5 into $VENV"
        python3 -m venv "$VENV"
        "$VENV/bin/python" -m pip --disable-pip-version-check -q install milvus==2.3.5
    fi
    mkdir -p "$DATA"
    # the embedded etcd's ports come from its own config file (milvus-server cannot set them)
    cat >"$DATA/etcd.yaml" <<EOF
name: pairvpr
listen-client-urls: http://127.0.0.1:$((2379 + SHIFT))
advertise-client-urls: http://127.0.0.1:$((2379 + SHIFT))
listen-peer-urls: http://127.0.0.1:$((2380 + SHIFT))
initial-advertise-peer-urls: http://127.0.0.1:$((2380 + SHIFT))
initial-cluster: pairvpr=http://127.0.0.1:$((2380 + SHIFT))
EOF
    ports=()
    for pair in proxy:19530 proxy-internal:19529 etcd:2379 root-coord:53100 query-coord:19531 \
        query-node:21123 index-coord:22930 index-node:21121 data-coord:13333 data-node:21124; do
        ports+=("--${pair%%:*}-port" "$((${pair#*:} + SHIFT))")
    done
    auth=()
    [ "${MILVUS_AUTH:-0}" = 1 ] && auth=(--authorization-enabled true)
    ETCD_CONFIG_PATH="$(realpath "$DATA/etcd.yaml")" setsid "$VENV/bin/python" \
        scripts/milvus_launch.py "$HEALTH_PORT" --data "$(realpath "$DATA")" "${ports[@]}" \
        "${auth[@]}" --extra-config common.gracefulStopTimeout=10 >"$DATA/server.log" 2>&1 &
    echo $! >"$PIDFILE"
    start_s=$SECONDS
    until healthy; do
        if ! kill -0 "$(cat "$PIDFILE")" 2>/dev/null; then
            echo "milvus: the server exited before it was healthy; last lines of $DATA/server.log:"
            tail -n 20 "$DATA/server.log"
            rm -f "$PIDFILE"
            return 1
        fi
        if ((SECONDS - start_s > TIMEOUT)); then
            echo "milvus: not healthy after ${TIMEOUT} s (MILVUS_START_TIMEOUT); stopping it;" \
                "last lines of $DATA/server.log:"
            tail -n 20 "$DATA/server.log"
            stop
            return 1
        fi
        sleep 1
    done
    echo "milvus: healthy after $((SECONDS - start_s)) s (pid $(cat "$PIDFILE"))," \
        "client URI http://127.0.0.1:$((19530 + SHIFT))"
}

case "${1:-}" in
start) start ;;
stop) stop ;;
status) healthy && echo "milvus: healthy" || { echo "milvus: not answering"; exit 1; } ;;
*) echo "usage: $0 start|stop|status" >&2; exit 2 ;;
esac
