#!/usr/bin/env bash
# Regenerate the committed gRPC stubs of tdcr/oip_grpc/open_inference_grpc.proto with grpcio-tools
# (the dev extra pins the version).  Usage: scripts/generate-grpc.sh [OUT_DIR] (default: the repository).
# tests/service/test_grpc.py regenerates them into a temporary folder and checks they match what is committed.
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-.}"
python=${PYTHON:-.venv/bin/python}
"$python" -m grpc_tools.protoc -I . --python_out="$out" --pyi_out="$out" --grpc_python_out="$out" \
  tdcr/oip_grpc/open_inference_grpc.proto
