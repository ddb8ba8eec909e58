#!/usr/bin/env bash
# Start a local Prefect server (127.0.0.1 only), create the `marionette-local` process work pool,
# deploy infra/prefect.yaml and start a worker. Everything runs in the background; logs and pid
# files go to $PREFECT_HOME/local/.
#
#   infra/start-local.sh            start server + pool + deployments + worker
#   infra/start-local.sh stop       stop the worker and the server started here
#   infra/start-local.sh env        print the exports a shell needs to talk to this server
#
# Settings (environment):
#   PREFECT_HOME        Prefect's state: database, results, profiles
#                       (default ${XDG_STATE_HOME:-$HOME/.local/state}/marionette/prefect)
#   MARIONETTE_PREFECT_PORT   API port on 127.0.0.1 (default 4200)
#   MARIONETTE_POOL     work pool name (default marionette-local)
#   PREFECT             the prefect executable (default: .venv/bin/prefect in the repo, else `prefect`)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export PREFECT_HOME="${PREFECT_HOME:-${XDG_STATE_HOME:-$HOME/.local/state}/marionette/prefect}"
PORT="${MARIONETTE_PREFECT_PORT:-4200}"
POOL="${MARIONETTE_POOL:-marionette-local}"
if [[ -z "${PREFECT:-}" ]]; then
  if [[ -x "$ROOT/.venv/bin/prefect" ]]; then PREFECT="$ROOT/.venv/bin/prefect"; else PREFECT=prefect; fi
fi
RUN="$PREFECT_HOME/local"
mkdir -p "$RUN"

export PREFECT_API_URL="http://127.0.0.1:$PORT/api"
export PREFECT_SERVER_API_HOST=127.0.0.1
export PREFECT_SERVER_API_PORT="$PORT"
export PREFECT_API_DATABASE_CONNECTION_URL="${PREFECT_API_DATABASE_CONNECTION_URL:-sqlite+aiosqlite:///$PREFECT_HOME/prefect.db}"
export PREFECT_SERVER_ANALYTICS_ENABLED=false
export DO_NOT_TRACK=1

stop_one() {  # stop_one NAME: interrupt the process group recorded in NAME.pid (a Prefect worker
  local f="$RUN/$1.pid"  # shuts down on SIGINT, not SIGTERM), then kill it after 15 s
  if [[ -f "$f" ]]; then
    local pid
    pid="$(cat "$f")"
    if kill -0 "$pid" 2>/dev/null; then
      kill -INT -- "-$pid" 2>/dev/null || kill -INT "$pid" 2>/dev/null || true
      for _ in $(seq 1 30); do
        kill -0 "$pid" 2>/dev/null || break
        sleep 0.5
      done
      kill -KILL -- "-$pid" 2>/dev/null || true
      echo "stopped $1 (pid $pid)"
    fi
    rm -f "$f"
  fi
}

case "${1:-start}" in
  stop)
    stop_one worker
    stop_one server
    exit 0
    ;;
  env)
    echo "export PREFECT_HOME='$PREFECT_HOME'"
    echo "export PREFECT_API_URL='$PREFECT_API_URL'"
    exit 0
    ;;
  start) ;;
  *)
    echo "usage: $0 [start|stop|env]" >&2
    exit 2
    ;;
esac

healthy() { curl -fsS "$PREFECT_API_URL/health" >/dev/null 2>&1; }

if healthy; then
  echo "Prefect server already answers at $PREFECT_API_URL"
else
  echo "starting Prefect server on 127.0.0.1:$PORT (PREFECT_HOME=$PREFECT_HOME, log $RUN/server.log)"
  setsid "$PREFECT" server start --host 127.0.0.1 --port "$PORT" >"$RUN/server.log" 2>&1 </dev/null &
  echo $! >"$RUN/server.pid"
  for _ in $(seq 1 120); do
    healthy && break
    sleep 1
  done
  healthy || { echo "server did not become healthy in 120 s; see $RUN/server.log" >&2; exit 1; }
fi

"$PREFECT" work-pool inspect "$POOL" >/dev/null 2>&1 || "$PREFECT" work-pool create "$POOL" --type process
cd "$ROOT"  # deployments record this directory as the flows' working directory
"$PREFECT" deploy --no-prompt --prefect-file infra/prefect.yaml --all

if [[ -f "$RUN/worker.pid" ]] && kill -0 "$(cat "$RUN/worker.pid")" 2>/dev/null; then
  echo "worker already running (pid $(cat "$RUN/worker.pid"))"
else
  echo "starting worker for pool $POOL (log $RUN/worker.log)"
  setsid "$PREFECT" worker start --pool "$POOL" --type process >"$RUN/worker.log" 2>&1 </dev/null &
  echo $! >"$RUN/worker.pid"
fi

cat <<MSG

Prefect is up. In another shell:
  export PREFECT_HOME='$PREFECT_HOME' PREFECT_API_URL='$PREFECT_API_URL'
  prefect deployment run build-corpus/local -p source=/path/to/wildworld -p corpus=/path/to/corpus
Stop with: $0 stop
MSG
