#!/usr/bin/env bash
# Reproduce the shipped demo model pair_vpr_ros/demo/assets/demo-small.pth on a CPU:
#   make demo-model        (or: bash scripts/train_demo_model.sh)
# 1. synthetic place datasets from world seeds 101-104 (the demo bag uses seed 7: never trained on)
# 2. stage one (Siamese masked image modelling), 3. stage two (global + pair classifier),
# 4. export as float16 with its config and a training summary beside it.
set -euo pipefail
cd "$(dirname "$0")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
PY=${PY:-.venv/bin/python}
OUT=${OUT:-demo_train}
STAGE1_STEPS=${STAGE1_STEPS:-120}
STAGE2_STEPS=${STAGE2_STEPS:-600}
COMMON=(--arch small --image-size 112 --train-blocks 4 --workers 1 --device cpu --seed 0
        --log-every 10 --checkpoint-every 0)

data=()
for seed in 101 102 103 104; do
    root="$OUT/data/world$seed"
    [ -d "$root" ] || "$PY" -m pair_vpr_ros.demo.make_bag --dataset "$root" --seed "$seed" \
        --places 150 --views 6 --size 160x120
    data+=(--data "folders:$root")
done

"$PY" -m pair_vpr_ros.train.stage1 "${data[@]}" "${COMMON[@]}" --out "$OUT/stage1" \
    --max-steps "$STAGE1_STEPS" --places-per-batch 32 --lr 5e-4 --warmup-steps 12
"$PY" -m pair_vpr_ros.train.stage2 "${data[@]}" "${COMMON[@]}" --out "$OUT/stage2" \
    --init "$OUT/stage1/stage1_final.pt" --max-steps "$STAGE2_STEPS" --places-per-batch 16 \
    --lr 5e-4 --save-every 50
"$PY" scripts/export_demo_model.py "$OUT" pair_vpr_ros/demo/assets/demo-small.pth
