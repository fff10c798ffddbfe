#!/usr/bin/env bash
# Install everything (serving, data, training with CPU torch, design search, dev tools) and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh serve,data,train,design,dev
.venv/bin/ruff check .
exec .venv/bin/python -m pytest -q "$@"
