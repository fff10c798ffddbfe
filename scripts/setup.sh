#!/usr/bin/env bash
# Create .venv (if needed) and install the project with the given extras, e.g. `scripts/setup.sh serve,train,dev`.
# torch is pinned to 2.13.0 in pyproject.toml: on these machines pip takes the CPU build from local disk.
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-serve}"
python3 -m venv .venv
stamp=".venv/.installed-$(echo "$extras" | tr ',' '-')-$(sha256sum pyproject.toml | cut -c1-12)"
if [ ! -f "$stamp" ]; then
  .venv/bin/python -m pip install --quiet --upgrade pip
  .venv/bin/python -m pip install --quiet -e ".[${extras}]"
  touch "$stamp"
fi
