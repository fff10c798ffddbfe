#!/usr/bin/env bash
# Install what serving needs, then start the service on the shipped models: HTTP on $PORT (default 8000)
# and gRPC (OIP v2) on $GRPC_PORT (default 8001).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh serve
exec .venv/bin/tdcr serve --host "${HOST:-127.0.0.1}" --port "${PORT:-8000}" --grpc-port "${GRPC_PORT:-8001}"
