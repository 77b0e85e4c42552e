#!/usr/bin/env bash
# `make demo`: render the synthetic loop world (seed 7, never used in training), write it as a
# rosbag2 MCAP, replay it through the loop-closure pipeline with the shipped demo model (loops
# with relative poses from depth), then correct the drifting /odom with those loops in the GTSAM
# pose graph and compare both with /ground_truth.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:-.venv}
OUT=${OUT:-demo_out}
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST MPLBACKEND=Agg

"$VENV/bin/pairvpr-make-demo-bag" "$OUT/demo_world.mcap" --seed 7 --frames 600 --force
"$VENV/bin/pairvpr-bag-replay" "$OUT/demo_world.mcap" --topic /camera/image_raw \
    --weights pair_vpr_ros/demo/assets/demo-small.pth --params-file config/demo.yaml \
    --pose-topic /odom --gt-topic /ground_truth --out "$OUT/replay" --overwrite
# The demo camera is an optical frame 1.6 m above base_link (the odometry's child frame).
"$VENV/bin/pairvpr-posegraph" "$OUT/demo_world.mcap" --loops "$OUT/replay" \
    --odom-topic /odom --gt-topic /ground_truth --camera-to-base "0 0 1.6 -0.5 0.5 -0.5 0.5" \
    --out "$OUT/posegraph"
echo "demo: pictures in $OUT/replay/trajectory.png, $OUT/replay/pr_curve.png and" \
    "$OUT/posegraph/posegraph.png; trajectories in $OUT/posegraph/*.tum; every decision in" \
    "$OUT/replay/report/index.html (open it in a browser); a threshold chosen on this bag in" \
    "$OUT/replay/suggested_params.yaml"
