#!/usr/bin/env bash
# A running Docker engine and the offline base image: usage scripts/docker-base.sh [IMAGE]
# (default tdcr-base:bookworm).  As root: installs Debian's docker.io, docker-compose and mmdebstrap
# when missing, starts dockerd when no engine answers, and builds IMAGE from Debian packages
# (mmdebstrap minbase + python3, python3-venv, ca-certificates; no docs, man pages or locales)
# -> docker import, unless it exists.  No image registry is needed.
set -euo pipefail
BASE=${1:-tdcr-base:bookworm}
if ! command -v dockerd >/dev/null || ! command -v docker-compose >/dev/null || ! command -v mmdebstrap >/dev/null; then
  DEBIAN_FRONTEND=noninteractive apt-get install -y -q docker.io docker-compose mmdebstrap >/dev/null
fi
if ! docker info >/dev/null 2>&1; then
  (dockerd >/tmp/dockerd.log 2>&1 &)
  for _ in $(seq 60); do docker info >/dev/null 2>&1 && break; sleep 1; done
  docker info >/dev/null 2>&1 || { tail -20 /tmp/dockerd.log >&2; echo "dockerd did not start" >&2; exit 1; }
fi
if ! docker image inspect "$BASE" >/dev/null 2>&1; then
  [ "$BASE" = tdcr-base:bookworm ] || { echo "base image $BASE not found" >&2; exit 1; }
  tar=$(mktemp --suffix=.tar)
  trap 'rm -f "$tar"' EXIT
  mmdebstrap --quiet --variant=minbase --include=python3,python3-venv,ca-certificates \
    --dpkgopt='path-exclude=/usr/share/doc/*' --dpkgopt='path-exclude=/usr/share/man/*' \
    --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-exclude=/usr/share/info/*' \
    bookworm "$tar" http://deb.debian.org/debian
  docker import "$tar" "$BASE" >/dev/null
fi
echo "docker engine up; base image $BASE"
