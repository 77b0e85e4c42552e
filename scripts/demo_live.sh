#!/usr/bin/env bash
# `make demo-live`: the demo through a real ROS 2 graph. vpr_node and posegraph_node run as two
# processes talking over DDS, started with the parameters and remappings vpr_posegraph.launch.py
# gives them (both read pair_vpr_ros/ros/launch_table.py); pairvpr-bag-play plays the demo bag
# into them in real time; the loops, factors and the pose graph's ATE are compared with
# `make demo`'s (made first when $OUT has none) and written to $OUT/live/summary.json.
#   RATE=1.0     bag play speed (1 = real time, 10 Hz)
#   LAUNCH=1     start the nodes with `ros2 launch pair_vpr_ros vpr_posegraph.launch.py` (needs
#                a ROS install or the environment of scripts/ros_cli_env.sh, docs/launch.md)
#   ROS_DOMAIN_ID  default: one of 20-99 at random, so other ROS processes stay out
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:-.venv}
OUT=${OUT:-demo_out}
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST MPLBACKEND=Agg
export ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$((RANDOM % 80 + 20))}

if [ ! -f "$OUT/demo_world.mcap" ] || [ ! -f "$OUT/replay/loops.csv" ]; then
    echo "demo-live: no $OUT/replay yet: running make demo's steps first"
    OUT="$OUT" bash scripts/demo.sh "$VENV"
fi
launch=()
if [ "${LAUNCH:-0}" = 1 ]; then
    launch=(--launch)
fi
echo "demo-live: ROS_DOMAIN_ID=$ROS_DOMAIN_ID, rate ${RATE:-1.0}${LAUNCH:+, LAUNCH=$LAUNCH}"
"$VENV/bin/python" -m pair_vpr_ros.demo.live "$OUT/demo_world.mcap" --replay "$OUT/replay" \
    --out "$OUT/live" --rate "${RATE:-1.0}" "${launch[@]}"
