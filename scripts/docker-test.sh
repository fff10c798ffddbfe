#!/usr/bin/env bash
# Build the service image offline and check it for real (issue: the deployment, run for real):
#   1. a Debian base image from Debian's packages (mmdebstrap -> docker import), unless BASE_IMAGE is set;
#   2. the serving wheels, built on this host (pip wheel) into docker/wheelhouse/;
#   3. the image (docker/Dockerfile, BASE_IMAGE build argument), offline (--no-index);
#   4. one container, non-root with a read-only root filesystem and a tmpfs /tmp, published on
#      127.0.0.1 only: wait for its HEALTHCHECK, then Triton's HTTP and gRPC clients on every model;
#   5. docker/compose.yaml with 2 replicas: the same checks against each.
# Needs the dev extras in .venv (tritonclient) and what scripts/docker-base.sh needs (root, apt packages
# docker.io, docker-compose and mmdebstrap).  Prints build time and image size.
set -euo pipefail
cd "$(dirname "$0")/.."
IMAGE=${IMAGE:-tdcr-surrogates:0.1.0}
BASE=${BASE_IMAGE:-tdcr-base:bookworm}
PY=.venv/bin/python
say() { printf '\n== %s\n' "$*"; }

bash scripts/docker-base.sh "$BASE"

say "wheels for the serving extras (docker/wheelhouse/)"
$PY -m pip wheel --quiet -w docker/wheelhouse ".[serve]" pip "setuptools>=68" 2>&1 | { grep -v "^WARNING: Location" || true; }

say "image $IMAGE (base $BASE, offline)"
started=$(date +%s)
previous=$(docker image inspect --format '{{.Id}}' "$IMAGE" 2>/dev/null || true)
docker build --quiet --build-arg BASE_IMAGE="$BASE" -f docker/Dockerfile -t "$IMAGE" . >/dev/null
# what a rebuild leaves behind (about 1.4 GB a run): the untagged build stage, and the image this tag named before
docker image prune --force --filter label=tdcr-surrogates.stage=build >/dev/null
if [ -n "$previous" ] && [ "$previous" != "$(docker image inspect --format '{{.Id}}' "$IMAGE")" ]; then
  docker image rm "$previous" >/dev/null 2>&1 || true  # kept while a container or another tag uses it
fi
echo "build: $(( $(date +%s) - started )) s; size: $(docker image inspect "$IMAGE" --format '{{.Size}}' | awk '{printf "%.0f MB", $1/1e6}')"

wait_healthy() {  # container id
  for _ in $(seq 120); do
    state=$(docker inspect --format '{{.State.Health.Status}}' "$1")
    [ "$state" = healthy ] && return 0
    [ "$state" = unhealthy ] && break
    sleep 1
  done
  docker logs "$1" | tail -30 >&2
  echo "container $1 is not healthy ($state)" >&2
  return 1
}

check() {  # container id: Triton's clients over both protocols, on the ports published on 127.0.0.1
  local http grpc user
  http=$(docker port "$1" 8000/tcp | grep 127.0.0.1 | head -1)
  grpc=$(docker port "$1" 8001/tcp | grep 127.0.0.1 | head -1)
  user=$(docker exec "$1" id -u)
  [ "$user" != 0 ] || { echo "container runs as root" >&2; return 1; }
  if docker exec "$1" touch /app/written 2>/dev/null; then echo "root filesystem is writable" >&2; return 1; fi
  $PY examples/tritonclient_http.py "http://$http" >/dev/null
  $PY examples/tritonclient_grpc.py "$grpc" >/dev/null
  echo "ok: $1 (uid $user, read-only root): tritonclient HTTP on $http and gRPC on $grpc, every model"
}

say "one container: non-root, read-only root filesystem"
cid=$(docker run -d --read-only --tmpfs /tmp --user 10001 -p 127.0.0.1::8000 -p 127.0.0.1::8001 "$IMAGE")
trap 'docker rm -f "$cid" >/dev/null 2>&1 || true' EXIT
wait_healthy "$cid"
check "$cid"
docker rm -f "$cid" >/dev/null

say "docker/compose.yaml, 2 replicas"
compose() { docker-compose -f docker/compose.yaml -p tdcr-test "$@"; }
trap 'compose down --remove-orphans >/dev/null 2>&1 || true' EXIT
compose up -d --no-build --scale tdcr=2 >/dev/null 2>&1
ids=$(compose ps -q tdcr)
[ "$(echo "$ids" | wc -l)" = 2 ] || { echo "expected 2 replicas, got: $ids" >&2; exit 1; }
for id in $ids; do wait_healthy "$id"; check "$id"; done
say "all container checks passed"
