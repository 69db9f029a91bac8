#!/usr/bin/env bash
# Starts the image as the gateway, a Ray head, or a Ray worker node; anything else runs as given.
set -euo pipefail
mode="${1:-gateway}"
shift || true
case "$mode" in
  gateway)
    exec rangeret serve --host "${RANGERET_HOST:-0.0.0.0}" --port "${RANGERET_PORT:-8000}" "$@"
    ;;
  ray-head)
    exec ray start --head --block --port 6379 --dashboard-host 0.0.0.0 --num-gpus 0 "$@"
    ;;
  ray-worker)
    exec ray start --block "$@"
    ;;
  *)
    exec "$mode" "$@"
    ;;
esac
