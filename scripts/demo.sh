#!/usr/bin/env bash
# `make demo`: render the synthetic loop world (seed 7, never used in training), write it as a
# rosbag2 MCAP, and replay it through the loop-closure pipeline with the shipped demo model.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:-.venv}
OUT=${OUT:-demo_out}
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST MPLBACKEND=Agg

"$VENV/bin/pairvpr-make-demo-bag" "$OUT/demo_world.mcap" --seed 7 --frames 600 --force
"$VENV/bin/pairvpr-bag-replay" "$OUT/demo_world.mcap" \
    --weights pair_vpr_ros/demo/assets/demo-small.pth --params-file config/demo.yaml \
    --pose-topic /odom --out "$OUT/replay"
echo "demo: pictures in $OUT/replay/trajectory.png and $OUT/replay/pr_curve.png"
