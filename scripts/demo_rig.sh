#!/usr/bin/env bash
# `make demo-rig` (issue 49): the demo world with a rear camera too and lap 1 driven the other way
# round, replayed with the front camera alone and with front + rear (one map, loops across
# cameras, in base_link), each corrected by the pose graph; the table compares them and
# demo_out/rig/rig_summary.json keeps it. The front-only run is make demo's single-camera
# pipeline on this world (the bag has two depth and camera_info topics: it names the front
# camera's); its loops are between camera frames, so its pose graph gets --camera-to-base; the
# rig's loops are in base_link already, so its pose graph gets none.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:-.venv}
OUT=${OUT:-demo_out}/rig
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST MPLBACKEND=Agg
REPLAY=("$VENV/bin/pairvpr-bag-replay" "$OUT/rig_world.mcap"
    --weights pair_vpr_ros/demo/assets/demo-small.pth --params-file config/demo.yaml
    --pose-topic /odom --gt-topic /ground_truth --overwrite)
POSEGRAPH=("$VENV/bin/pairvpr-posegraph" "$OUT/rig_world.mcap" --odom-topic /odom
    --gt-topic /ground_truth)

"$VENV/bin/pairvpr-make-demo-bag" "$OUT/rig_world.mcap" --seed 7 --frames 600 --rig --force
"${REPLAY[@]}" --topic /camera/image_raw --depth-topic /camera/depth/image_raw \
    --camera-info-topic /camera/camera_info --out "$OUT/front_only"
"${REPLAY[@]}" --rig config/demo_rig.yaml --out "$OUT/rig"
"${POSEGRAPH[@]}" --loops "$OUT/front_only" --camera-to-base "0 0 1.6 -0.5 0.5 -0.5 0.5" \
    --out "$OUT/front_only_posegraph"
"${POSEGRAPH[@]}" --loops "$OUT/rig" --out "$OUT/rig_posegraph"
"$VENV/bin/python" -m pair_vpr_ros.demo.rig_summary "$OUT"
echo "demo-rig: $OUT/rig_summary.json; pictures in $OUT/*_posegraph/posegraph.png"
