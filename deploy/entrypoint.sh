#!/usr/bin/env bash
# The image's entrypoint. Modes:
#   gateway (default)   rangeret serve on 0.0.0.0:8000 (RANGERET_HOST, RANGERET_PORT) with the
#                       options given after it
#   ray-head            a Ray head node, blocking: for plain `docker run` only
#   ray-worker          a Ray node that joins a head (--address HEAD:6379): plain `docker run` only
#   anything else       runs as a command (`ray job submit ...`, `rangeret predict ...`, `bash`)
# On KubeRay the Ray containers do not come here: KubeRay replaces the container's command with its
# own `/bin/bash -c -- "ulimit ...; ray start ..."` built from rayStartParams.
set -euo pipefail
mode="${1:-gateway}"
shift || true
case "$mode" in
  gateway)
    exec rangeret serve --host "${RANGERET_HOST:-0.0.0.0}" --port "${RANGERET_PORT:-8000}" "$@"
    ;;
  ray-head)
    exec ray start --head --block --port=6379 --dashboard-host=0.0.0.0 --num-gpus=0 "$@"
    ;;
  ray-worker)
    exec ray start --block "$@"
    ;;
  *)
    exec "$mode" "$@"
    ;;
esac
