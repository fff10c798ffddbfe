#!/usr/bin/env bash
# Install what serving needs, then run the main job on the shipped defaults.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh serve,data
exec .venv/bin/tdcr solve examples/request.json
