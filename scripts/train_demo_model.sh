#!/usr/bin/env bash
# Reproduce the shipped demo model pair_vpr_ros/demo/assets/demo-small.pth on a CPU:
#   make demo-model        (or: bash scripts/train_demo_model.sh)
# 1. synthetic place datasets from world seeds 101-104 (the demo bag uses seed 7, the demo settings
#    were chosen on seed 8 and the tests use seed 11: none of them is trained on);
# 2. encoder pre-training: the paper starts stage one from DINOv2, which has no 128-d model, so
#    the small encoder first learns places from a random init with stage two's global loss alone
#    (no augmentation and a warm-up: from scratch the global descriptor otherwise collapses);
# 3. stage one (Siamese masked image modelling) from that encoder, as from DINOv2;
# 4. stage two (global descriptor + pair classifier) from stage one;
# 5. export as float16 with its config and a training summary beside it.
set -euo pipefail
cd "$(dirname "$0")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
PY=${PY:-.venv/bin/python}
OUT=${OUT:-demo_train}
PRETRAIN_STEPS=${PRETRAIN_STEPS:-1800}
STAGE1_STEPS=${STAGE1_STEPS:-300}
STAGE2_STEPS=${STAGE2_STEPS:-400}
COMMON=(--arch small --image-size 112 --workers 1 --device cpu --seed 0 --log-every 10
        --checkpoint-every 0 --epochs 1000)

data=()
for seed in 101 102 103 104; do
    root="$OUT/data/world$seed"
    [ -d "$root" ] || "$PY" -m pair_vpr_ros.demo.make_bag --dataset "$root" --seed "$seed" \
        --places 150 --views 6 --size 160x120
    data+=(--data "folders:$root")
done

# A stage whose final weights exist is not run again (delete OUT/<stage> to redo it).
[ -f "$OUT/pretrain/stage2_final.pt" ] ||
"$PY" -m pair_vpr_ros.learn.train.stage2 "${data[@]}" "${COMMON[@]}" --out "$OUT/pretrain" \
    --train-blocks 4 --max-steps "$PRETRAIN_STEPS" --places-per-batch 32 --lr 1e-3 \
    --warmup-steps 50 --pair-weight 0 --no-augment --save-every 200
"$PY" scripts/export_encoder.py "$OUT/pretrain/stage2_final.pt" "$OUT/pretrain/encoder_reg4.pth"
[ -f "$OUT/stage1/stage1_final.pt" ] ||
"$PY" -m pair_vpr_ros.learn.train.stage1 "${data[@]}" "${COMMON[@]}" --out "$OUT/stage1" \
    --dinov2 "$OUT/pretrain/encoder_reg4.pth" --train-blocks 2 --max-steps "$STAGE1_STEPS" \
    --places-per-batch 32 --lr 5e-4 --warmup-steps 30
[ -f "$OUT/stage2/stage2_final.pt" ] ||
"$PY" -m pair_vpr_ros.learn.train.stage2 "${data[@]}" "${COMMON[@]}" --out "$OUT/stage2" \
    --init "$OUT/stage1/stage1_final.pt" --train-blocks 2 --max-steps "$STAGE2_STEPS" \
    --places-per-batch 32 --lr 5e-4 --warmup-steps 20 --no-augment --save-every 100
"$PY" scripts/export_demo_model.py "$OUT" pair_vpr_ros/demo/assets/demo-small.pth
