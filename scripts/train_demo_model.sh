#!/usr/bin/env bash
# Reproduce the shipped demo model pair_vpr_ros/demo/assets/demo-small.pth:
#   make demo-model        (or: bash scripts/train_demo_model.sh; hours on a CPU)
#   DEVICE=cuda WORKERS=12 JOBS=16 bash scripts/train_demo_model.sh   (minutes on a GPU machine:
#                          how the shipped model was made)
# Recipe and its cost: docs/training.md. In short:
# 1. synthetic place datasets from world seeds 101-132 and a held-out world, seed 201 (the demo
#    bag uses seed 7, the demo settings were chosen on seed 8 and the tests use seed 11: none of
#    them is trained or measured on during training);
# 2. encoder pre-training: the paper starts stage one from DINOv2, which has no 128-d model, so
#    the small encoder first learns places from a random init with stage two's global loss and a
#    loss on its mean patch token (so that the patch tokens the pair classifier reads carry the
#    place too), no jitter, a warm-up, half the places all grey (mono8 cameras);
# 3. stage one (Siamese masked image modelling, the authors' optimiser) from that encoder;
# 4. stage two from stage one: global descriptor + pair classifier, mined without the lighting
#    shortcut (--conditions 3), identical / near-identical pairs as positives (--twin-share),
#    half the places all grey, re-ranked vs global AP on the held-out world (colour and grey)
#    every EVAL_EVERY steps;
# 5. stage two on drives (docs/training.md): drive bags of the training worlds 101-124 (101-112
#    also as mono8) and of the held-out world 201, replayed with the stage-two model; only the
#    pair classifier is fine-tuned, on each keyframe's global top-K (what re-ranking in the node
#    faces) and on keyframes of new ground (PAIR_TUNE_LONELY a step, so that a first visit
#    scores low), with AP on the held-out drive every PAIR_TUNE_EVAL_EVERY steps;
# 6. export as float16 with its config and a training summary beside it.
# Every stage is resumable: re-running the script skips finished stages and continues an
# interrupted one from OUT/<stage>/last.pt (written every SAVE_EVERY steps).
set -euo pipefail
cd "$(dirname "$0")/.."
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
PY=${PY:-.venv/bin/python}
OUT=${OUT:-demo_train}
DEST=${DEST:-pair_vpr_ros/demo/assets/demo-small.pth}
PRETRAIN_STEPS=${PRETRAIN_STEPS:-2350}
STAGE1_STEPS=${STAGE1_STEPS:-950}
STAGE2_STEPS=${STAGE2_STEPS:-4700}
STAGE2_PLACES=${STAGE2_PLACES:-16}  # places per stage-two batch (x 4 views)
PAIR_NEGATIVES=${PAIR_NEGATIVES:-random}  # hardest (the paper) or random: docs/training.md
STAGE2_LR=${STAGE2_LR:-2.5e-4}
# Grey (mono8) cameras, docs/training.md: share of places whose views are ALL grey in the
# encoder pre-training, stage one and stage two; per-view grey shares (stage two; pre-training
# and stage one: EARLY_GREY), which the grey places replace; the worlds of the place datasets.
GREY_PLACES=${GREY_PLACES:-0.5}
STAGE2_GREY=${STAGE2_GREY:-0}
EARLY_GREY=${EARLY_GREY:-0}
WORLD_SEEDS=${WORLD_SEEDS:-$(seq -s ' ' 101 132)}
GREY_DRIVE_SEEDS=${GREY_DRIVE_SEEDS:-$(seq -s ' ' 101 112)}  # drives also replayed as mono8
PAIR_TUNE_STEPS=${PAIR_TUNE_STEPS:-2400}
PAIR_TUNE_LONELY=${PAIR_TUNE_LONELY:-32}  # keyframes of new ground a step (pair_tune --lonely)
PAIR_TUNE_TWINS=${PAIR_TUNE_TWINS:-8}  # identical pairs a step (pair_tune --twins)
PAIR_TUNE_EVAL_EVERY=${PAIR_TUNE_EVAL_EVERY:-600}
# drives of these training worlds for the pair classifier (with 4 it over-fits in ~300 steps)
DRIVE_SEEDS=${DRIVE_SEEDS:-$(seq -s ' ' 101 124)}
DRIVE_FRAMES=${DRIVE_FRAMES:-600}  # frames of each drive bag (10 Hz)
SAVE_EVERY=${SAVE_EVERY:-100}
EVAL_EVERY=${EVAL_EVERY:-450}
# The machine: DEVICE (cpu, cuda) of the training stages, WORKERS (their data-loader workers)
# and JOBS (place datasets rendered, drives rendered and replayed at once); the shipped model:
# DEVICE=cuda WORKERS=12 JOBS=16 (docs/training.md). STOP_AFTER=stage2 ends the run after stage
# two (the drive stage can then run on another machine).
DEVICE=${DEVICE:-cpu}
WORKERS=${WORKERS:-1}
JOBS=${JOBS:-1}
STOP_AFTER=${STOP_AFTER:-}
case "$JOBS" in
    '' | 0 | *[!0-9]*) echo "error: JOBS must be a whole number >= 1, got '$JOBS'" >&2; exit 2 ;;
esac
case "$STOP_AFTER" in
    '' | stage2) ;;
    *) echo "error: STOP_AFTER must be empty or stage2, got '$STOP_AFTER'" >&2; exit 2 ;;
esac
COMMON=(--arch small --image-size 112 --workers "$WORKERS" --device "$DEVICE" --seed 0 --log-every 10
        --checkpoint-every 0 --epochs 100000 --save-every "$SAVE_EVERY" --conditions 3)

# spawn CMD...: run CMD in the background; at_most N: wait until fewer than N of those are
# unfinished (0: all), each reaped with wait -n so that a failed one stops the script (set -e),
# also one that ended before at_most was called
started=0 reaped=0
spawn() {
    "$@" &
    started=$((started + 1))
}
at_most() {
    while [ $((started - reaped)) -gt 0 ] && [ $((started - reaped)) -ge "$1" ]; do
        reaped=$((reaped + 1))
        wait -n
    done
}
# render_places ROOT SEED PLACES: one world's place dataset, unless it is there already
render_places() {
    [ -d "$1" ] || "$PY" -m pair_vpr_ros.demo.make_bag --dataset "$1" --seed "$2" --places "$3" \
        --views 6 --size 160x120
}
data=()
HELDOUT="$OUT/data/heldout201"
for seed in $WORLD_SEEDS 201; do
    root="$OUT/data/world$seed" places=150
    [ "$seed" = 201 ] && root=$HELDOUT places=60
    [ "$seed" = 201 ] || data+=(--data "folders:$root")
    # a finished stage two needs no place datasets (a run continued from train_state/)
    [ -f "$OUT/stage2/stage2_final.pt" ] && continue
    at_most "$JOBS"
    spawn render_places "$root" "$seed" "$places"
done
at_most 0

# run_stage DIR FINAL MODULE ARGS...: skip a finished stage, resume an interrupted one.
run_stage() {
    local dir=$1 final=$2 module=$3
    shift 3
    [ -f "$OUT/$dir/$final" ] && return 0
    local resume=()
    [ -f "$OUT/$dir/last.pt" ] && resume=(--resume "$OUT/$dir/last.pt")
    "$PY" -m "$module" "${data[@]}" "${COMMON[@]}" --out "$OUT/$dir" "${resume[@]}" "$@"
}

# The encoder pre-training is needed only until stage one has finished (a run continued from
# scripts/train_state.py's copy has stage one's weights but no pre-training output).
# INIT_ENCODER=<Pair-VPR weights>: take the encoder of those weights instead of pre-training one
# (a shortcut for a loaded machine; docs/training.md says which run used it).
if [ ! -f "$OUT/stage1/stage1_final.pt" ]; then
    if [ -n "${INIT_ENCODER:-}" ] && [ ! -f "$OUT/pretrain/encoder_reg4.pth" ]; then
        mkdir -p "$OUT/pretrain"
        "$PY" scripts/export_encoder.py "$INIT_ENCODER" "$OUT/pretrain/encoder_reg4.pth"
    fi
    [ -f "$OUT/pretrain/encoder_reg4.pth" ] ||
    run_stage pretrain stage2_final.pt pair_vpr_ros.learn.train.stage2 \
        --train-blocks 4 --max-steps "$PRETRAIN_STEPS" --places-per-batch 32 --lr 1e-3 \
        --warmup-steps 50 --pair-weight 0 --patch-weight 1.0 --no-augment --grey "$EARLY_GREY" \
        --grey-places "$GREY_PLACES"
    [ -f "$OUT/pretrain/encoder_reg4.pth" ] ||
    "$PY" scripts/export_encoder.py "$OUT/pretrain/stage2_final.pt" \
        "$OUT/pretrain/encoder_reg4.pth"
fi
# Stage one: the authors' optimiser (AdamW 0.9/0.999, layer decay 0.9 over encoder + decoder,
# weight decay 0.04 -> 0.4, cosine to 1e-6, no clipping) but a larger peak lr than their
# 3e-4 x sqrt(32 / 1024) = 5.3e-5: this run is a few hundred steps, not the authors' hundreds of
# epochs, so it keeps the peak lr of the earlier demo recipe (5e-4; docs/training.md).
run_stage stage1 stage1_final.pt pair_vpr_ros.learn.train.stage1 \
    --dinov2 "$OUT/pretrain/encoder_reg4.pth" --train-blocks 2 --max-steps "$STAGE1_STEPS" \
    --places-per-batch 32 --lr 5e-4 --warmup-steps 100 --no-augment --grey "$EARLY_GREY" \
    --grey-places "$GREY_PLACES"
run_stage stage2 stage2_final.pt pair_vpr_ros.learn.train.stage2 \
    --init "$OUT/stage1/stage1_final.pt" --train-blocks 4 --max-steps "$STAGE2_STEPS" \
    --places-per-batch "$STAGE2_PLACES" --lr "$STAGE2_LR" --warmup-steps 100 --no-augment --grey "$STAGE2_GREY" \
    --grey-places "$GREY_PLACES" \
    --patch-weight 0.5 --twin-share 0.25 --pair-directions first \
    --pair-negatives "$PAIR_NEGATIVES" \
    --heldout "$HELDOUT" --eval-every "$EVAL_EVERY"

[ "$STOP_AFTER" = stage2 ] && exit 0

# Stage two on drives: render each drive bag and replay it with the stage-two model (its map
# lands in DIR/map; an interrupted replay saves a partial map too, so DIR/drive.done marks a
# finished one and a drive without it is redone), then tune.
# Seeds 7 (demo) and 8 (validation of config/demo.yaml) are never used here.
replay() {
    "$PY" -m pair_vpr_ros.offline.replay.cli "$@"
}
# drive <seed>[g]: render world <seed>'s drive, in colour or ("g") as a mono8 camera sees it,
# and replay it (skipped when done)
drive() {
    local name=$1 seed=${1%g} mono=() run="$OUT/drives/replay$1"
    [ -f "$run/drive.done" ] && return 0
    [ "$name" != "$seed" ] && mono=(--mono)
    "$PY" -m pair_vpr_ros.demo.make_bag "$OUT/drives/world$name.mcap" --seed "$seed" \
        --frames "$DRIVE_FRAMES" --force "${mono[@]}"
    replay "$OUT/drives/world$name.mcap" --topic /camera/image_raw \
        --weights "$OUT/stage2/stage2_final.pt" --params-file config/demo.yaml \
        --pose-topic /ground_truth --gt-topic /ground_truth --top-k 1 --out "$run" \
        --overwrite --quiet
    touch "$run/drive.done"
}
if [ ! -f "$OUT/pair_tune/pair_tune_final.pt" ]; then
    for name in $DRIVE_SEEDS 201 $(for s in $GREY_DRIVE_SEEDS; do echo "${s}g"; done); do
        at_most "$JOBS"
        # one thread each when several run at once (replays are per-frame, small matrices)
        if [ "$JOBS" -gt 1 ]; then OMP_NUM_THREADS=1 spawn drive "$name"; else drive "$name"; fi
    done
    at_most 0
    resume=()
    [ -f "$OUT/pair_tune/last.pt" ] && resume=(--resume "$OUT/pair_tune/last.pt")
    drives=()
    for seed in $DRIVE_SEEDS; do drives+=(--drive "$OUT/drives/replay$seed/map"); done
    for seed in $GREY_DRIVE_SEEDS; do drives+=(--drive "$OUT/drives/replay${seed}g/map"); done
    "$PY" -m pair_vpr_ros.learn.train.pair_tune --init "$OUT/stage2/stage2_final.pt" \
        "${drives[@]}" --val "$OUT/drives/replay201/map" --out "$OUT/pair_tune" \
        --steps "$PAIR_TUNE_STEPS" --lonely "$PAIR_TUNE_LONELY" --twins "$PAIR_TUNE_TWINS" \
        --save-every "$SAVE_EVERY" --eval-every "$PAIR_TUNE_EVAL_EVERY" \
        --seed 0 --device "$DEVICE" "${resume[@]}"
fi
"$PY" -c "from pathlib import Path; from pair_vpr_ros.learn.train.curves import draw_curves; \
draw_curves([(s, Path('$OUT') / s / 'train_log.jsonl') \
for s in ('pretrain', 'stage1', 'stage2', 'pair_tune')], Path('$OUT') / 'curves.png')"
"$PY" scripts/export_demo_model.py "$OUT" "$DEST"
