#!/usr/bin/env bash
# Reproduce the shipped loaded operators (deeponet_pose_loaded, fno_pose_loaded) from scratch on a
# CPU machine (2 cores): an 80,000-design dataset in gravity and under tip loads
# (tdcr.robot.design_space.TRAINING_LOADS: |g| = 9.81 m/s^2 in a uniform direction, density
# 6,450-8,000 kg/m^3, tip loads on half the designs, a fifth unloaded), both operators trained side
# by side on one thread each (the DeepONet for 45 minutes, the FNO for 55), exported to models/,
# and evaluated on the held-out 20 % and on load-free Table I designs.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh serve,data,train,dev
data=${DATA:-data/tdcr-loaded-80k}
free=${FREE:-data/tdcr-100k}
runs=${RUNS:-runs}
models=${MODELS:-models}
.venv/bin/tdcr generate --n 80000 --seed 24 --out "$data" --gravity sphere --density 6450,8000 \
    --tip-force 0.02 --tip-moment 0.002 --tip-fraction 0.5 --unloaded-fraction 0.2 --quiet
train() { OMP_NUM_THREADS=1 .venv/bin/tdcr train --model "$1" --data "$data" --out "$runs/$1" --minutes "$2" --quiet; }
train deeponet_pose_loaded "${DEEPONET_MINUTES:-45}" & train fno_pose_loaded "${FNO_MINUTES:-55}" & wait
.venv/bin/tdcr export "$runs/deeponet_pose_loaded" "$runs/fno_pose_loaded" --data "$data" --models-dir "$models"
.venv/bin/tdcr evaluate --data "$data" --models-dir "$models" --update-manifest
.venv/bin/tdcr generate --n 100000 --seed 0 --out "$free" --quiet
.venv/bin/tdcr evaluate --data "$free" --models-dir "$models" --models deeponet_pose_loaded fno_pose_loaded \
    --update-manifest
