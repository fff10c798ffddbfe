#!/usr/bin/env bash
# Install what serving needs, then start the HTTP service on the shipped models (port $PORT, default 8000).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh serve
exec .venv/bin/tdcr serve --host "${HOST:-127.0.0.1}" --port "${PORT:-8000}"
