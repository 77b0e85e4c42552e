#!/usr/bin/env bash
# `make demo-fleet`: the demo world driven by a fleet (robots a, b, c on one clock from three
# points of the loop; robot a again a day later at dusk), each drive replayed with its own
# identity and the earlier drives' maps as prior maps, the fleet exchange between the robots'
# first sessions, then one pose graph of all robot-sessions.
# Writes demo_out/fleet/: the bags, replay/<robot>_<session>/, exchange/,
# posegraph/<robot>/<session>/*.tum,
# posegraph/posegraph.png (before/after) and summary.json (pairvpr docs: docs/posegraph-fleet.md).
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${1:-.venv}
OUT=${OUT:-demo_out}/fleet
FRAMES=${FRAMES:-300}
TOP_K=${TOP_K:-}  # e.g. TOP_K=10: re-rank 10 candidates (config/demo.yaml: 5)
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST MPLBACKEND=Agg
PY="$VENV/bin/python"

"$VENV/bin/pairvpr-make-demo-bag" "$OUT" --fleet --frames "$FRAMES" --force
# Identity (--robot-id/--session-id) and prior maps (--prior-map) come with issue 22's fleet
# work; a replay without them finds only the loops within its own drive.
HELP=$("$VENV/bin/pairvpr-bag-replay" --help)
IDENTITY=0 PRIOR=0
grep -q -- "--robot-id" <<<"$HELP" && IDENTITY=1
grep -q -- "--prior-map" <<<"$HELP" && PRIOR=1
[ "$IDENTITY$PRIOR" = 11 ] || echo "demo-fleet: this replay has no" \
    "$([ $IDENTITY = 1 ] || echo --robot-id) $([ $PRIOR = 1 ] || echo --prior-map):" \
    "loops between robots cannot be found; each drive is replayed alone" >&2

priors=() trajectories=() loops=()
while read -r robot session bag; do
    name="${robot}_${session}"
    extra=()
    [ -n "$TOP_K" ] && extra+=(--top-k "$TOP_K")
    [ $IDENTITY = 1 ] && extra+=(--robot-id "$robot" --session-id "$session")
    if [ $PRIOR = 1 ]; then for map in "${priors[@]}"; do extra+=(--prior-map "$map"); done; fi
    "$VENV/bin/pairvpr-bag-replay" "$OUT/$bag" --topic /camera/image_raw \
        --weights pair_vpr_ros/demo/assets/demo-small.pth --params-file config/demo.yaml \
        --pose-topic /odom --gt-topic /ground_truth --out "$OUT/replay/$name" --overwrite \
        --quiet "${extra[@]}"
    priors+=("$OUT/replay/$name/map")
    trajectories+=(--trajectory "$robot" "$session" "$OUT/$bag")
    loops+=(--loops-of "$robot" "$session" "$OUT/replay/$name")
done < <("$PY" -c 'import json, sys
for d in json.load(open(sys.argv[1]))["drives"]:
    print(d["robot"], d["session"], d["bag"])' "$OUT/fleet.json")

# Fleet exchange between the robots' first sessions (one clock): descriptors shared, candidates
# scored by their owner (config/demo.yaml's fleet_* settings: budget 4 requests per 10 s). Its
# loops add to the replays' (a later session relocalises through the prior maps above); each
# keyframe pair once: exchange/added_loops.json holds those no replay accepted.
exchange=() seen=" "
while read -r robot session bag; do
    case "$seen" in *" $robot "*) continue ;; esac
    seen+="$robot " exchange+=(--robot "$robot" "$session" "$OUT/$bag")
done < <("$PY" -c 'import json, sys
for d in json.load(open(sys.argv[1]))["drives"]:
    print(d["robot"], d["session"], d["bag"])' "$OUT/fleet.json")
"$VENV/bin/pairvpr-fleet-replay" "${exchange[@]}" --weights pair_vpr_ros/demo/assets/demo-small.pth \
    --params-file config/demo.yaml --topic /camera/image_raw --pose-topic /odom \
    --out "$OUT/exchange" --overwrite --quiet
"$PY" -m pair_vpr_ros.offline.fleet.loops "$OUT"

# The demo camera is an optical frame 1.6 m above base_link (the odometry's child frame).
"$VENV/bin/pairvpr-posegraph" "${trajectories[@]}" "${loops[@]}" \
    --loops "$OUT/exchange/added_loops.json" --odom-topic /odom \
    --gt-topic /ground_truth --camera-to-base "0 0 1.6 -0.5 0.5 -0.5 0.5" --out "$OUT/posegraph"
"$PY" -m pair_vpr_ros.offline.fleet.report "$OUT"
echo "demo-fleet: $OUT/summary.json, $OUT/posegraph/posegraph.png," \
    "$OUT/posegraph/<robot>/<session>/optimised.tum"
