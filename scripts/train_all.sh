#!/usr/bin/env bash
# Reproduce the shipped models from scratch on a CPU machine (2 cores): generate the 100,000-design
# dataset, train the four operators with the tuned preset, two at a time on one thread each
# (the FNOs for 40 minutes, then the DeepONets for 30), export them to models/ and evaluate them
# on the held-out 20 %.
#
# The loaded operators (gravity and a tip wrench): scripts/train_loaded.sh.
#
# The paper's hyperparameters instead, kept apart from the shipped models:
#   PRESET=paper RUNS=runs/paper MODELS=runs/paper/models bash scripts/train_all.sh
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh serve,data,train,dev
data=${DATA:-data/tdcr-100k}
preset=${PRESET:-tuned}
runs=${RUNS:-runs}
models=${MODELS:-models}
.venv/bin/tdcr generate --n 100000 --seed 0 --out "$data" --quiet
train() { OMP_NUM_THREADS=1 .venv/bin/tdcr train --model "$1" --preset "$preset" --data "$data" --out "$runs/$1" \
            --minutes "$2" --epochs 100000 --patience 100000 --quiet; }
train fno "${FNO_MINUTES:-40}" & train fno_pose "${FNO_MINUTES:-40}" & wait
train deeponet "${DEEPONET_MINUTES:-30}" & train deeponet_pose "${DEEPONET_MINUTES:-30}" & wait
.venv/bin/tdcr export "$runs/deeponet" "$runs/deeponet_pose" "$runs/fno" "$runs/fno_pose" --data "$data" \
    --models-dir "$models"
.venv/bin/tdcr evaluate --data "$data" --models-dir "$models" --ood 1000
