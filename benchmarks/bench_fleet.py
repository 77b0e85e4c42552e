"""Fleet exchange: bytes on the wire, and what a split bag's robots find between them.

    python benchmarks/bench_fleet.py                      # wire sizes only (no weights)
    python benchmarks/bench_fleet.py --bag demo_out/demo_world.mcap --robots 2 \\
        --weights pair_vpr_ros/demo/assets/demo-small.pth --params-file config/demo.yaml

Wire sizes: one keyframe descriptor, one score request (the query's dense tokens; with and
without 1000 SIFT keypoints with depth, as `fleet_send_features` sends them) and one response,
at the shapes of ViT-B/322 (Pair-VPR's released model), ViT-L/322 and the demo model.

With --bag: the bag's frames are split in time into --robots equal parts, one robot each, and
every part's clock is shifted to start at the bag's start (overlapping clocks); the robots are
replayed together with the exchange (`run_fleet`). Inter-robot loops are labelled true when the
two keyframes' --gt-topic positions are within --gt-radius m. Prints keyframes, bytes per
keyframe and per accepted loop, true / false loops and the run time.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

from pair_vpr_ros.fleet import KeyframeDescriptor, ScoreRequest, ScoreResponse, encode, model_tag
from pair_vpr_ros.geometry.features import Features, pack_features
from pair_vpr_ros.offline.bags.opening import open_bag

SESSION = "20261125T160000Z"
SHAPES = {"ViT-B/322": (529, 768), "ViT-L/322": (529, 1024), "demo-small/112": (64, 128)}


def sift_features(n: int = 1000) -> bytes:
    rng = np.random.default_rng(0)
    kp = rng.uniform(0, 320, (n, 2)).astype(np.float32)
    desc = rng.integers(0, 256, (n, 128), dtype=np.uint8)
    return pack_features(Features(kp, desc, "sift", rng.uniform(1, 9, n).astype(np.float32)))


def wire_sizes() -> None:
    tag, feats = model_tag("x"), sift_features()
    desc = KeyframeDescriptor("robot_1", SESSION, tag, 1234, 1.0, np.zeros(512, np.float16))
    print(f"keyframe descriptor, 512-d: {len(encode(desc)):,} B (robot 'robot_1', session "
          f"{SESSION!r})")  # fmt: skip
    for name, (n, d) in SHAPES.items():
        req = ScoreRequest("robot_2", SESSION, tag, 1, "robot_1", SESSION, 99, 1.0,
                           [1, 2, 3], [0.9, 0.8, 0.7], np.zeros((n, d), np.float16))  # fmt: skip
        plain = len(encode(req))
        req.features = feats
        print(f"score request {name:15s} [{n} x {d}] tokens: {plain:,} B; with 1000 SIFT "
              f"keypoints + depth ({len(feats):,} B): {len(encode(req)):,} B")  # fmt: skip
    resp = ScoreResponse("robot_1", SESSION, tag, 1, "robot_2", SESSION, 99, 1, 1.0, 3.5, 3,
                         True, "metric")  # fmt: skip
    print(f"score response: {len(encode(resp)):,} B")


def split_frames(bag: str, part: int, parts: int, args, truth: dict) -> object:
    """Frames of time slice `part` of `parts`, stamps shifted to start with the bag."""
    from pair_vpr_ros.offline.bags.sources import FrameCounts, source_frames

    with open_bag(bag) as reader:
        start, end = reader.start_time / 1e9, reader.end_time / 1e9
    width = (end - start) / parts
    lo, hi = start + part * width, start + (part + 1) * width
    for frame in source_frames(bag, FrameCounts(), args.topic, pose_topic=args.gt_topic):
        if lo <= frame.stamp < hi:
            frame.stamp -= part * width
            truth[(f"r{part}", frame.stamp)] = frame.pose
            yield frame


def fleet_run(args) -> None:
    from pair_vpr_ros.offline.fleet.replay import FleetRobot, run_fleet
    from pair_vpr_ros.params.configs import detector_config, geometry_config
    from pair_vpr_ros.params.file import read_params_file
    from pair_vpr_ros.weights import load_model

    values = read_params_file(args.params_file)
    model = load_model(args.weights)
    truth: dict = {}
    robots = [FleetRobot(f"r{i}", SESSION, split_frames(args.bag, i, args.robots, args, truth))
              for i in range(args.robots)]  # fmt: skip
    fleet = dict(budget=args.budget, period_s=args.period, top_k=args.top_k)
    t0 = time.perf_counter()
    run = run_fleet(robots, model, detector_config(values), fleet, geometry_config(values))
    seconds = time.perf_counter() - t0
    labels = []
    for loop in run.loops:
        if loop.record.accepted:
            q = truth[(loop.query_robot, loop.record.query_stamp)]
            m = truth[(loop.match_robot, loop.record.match_stamp)]
            labels.append(math.dist(q[:3], m[:3]) <= args.gt_radius)
    t = run.totals()
    poses = sum(1 for x in run.loops if x.record.accepted and x.record.pose_status)
    print(f"{args.robots} robots, {t['keyframes']} keyframes in {seconds:.0f} s "
          f"(load {os.getloadavg()[0]:.1f}); bytes sent: {t['bytes_sent']}")  # fmt: skip
    print(f"descriptor bytes per keyframe {t['descriptor_bytes_per_keyframe']:.0f}; all fleet "
          f"bytes per keyframe {t['bytes_per_keyframe']:.0f}; request + response bytes per "
          f"accepted loop {t['scoring_bytes_per_accepted_loop'] or 0:.0f}")  # fmt: skip
    print(f"inter-robot loops: {len(labels)} accepted ({sum(labels)} true, "
          f"{len(labels) - sum(labels)} false within {args.gt_radius} m, {poses} with a "
          f"relative pose), {t['inter_robot_rejected']} rejected by their owner")  # fmt: skip
    for robot, ex in run.exchanges.items():
        print(f"  {robot}: sent {dict(ex['sent'])}, skipped {ex['skipped']}, budget cut "
              f"{ex['budget_cut']}, timeouts {ex['timeouts']}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--bag", help="a bag to split into robots (else: wire sizes only)")
    p.add_argument("--robots", type=int, default=2, help="robots the bag is split into")
    p.add_argument("--weights", help="checkpoint for --bag")
    p.add_argument("--params-file", default="config/demo.yaml", help="vpr_node parameters")
    p.add_argument("--topic", default="/camera/image_raw", help="image topic")
    p.add_argument("--gt-topic", default="/ground_truth", help="true poses")
    p.add_argument("--gt-radius", type=float, default=10.0, help="true loop: within this, m")
    p.add_argument("--budget", type=int, default=4, help="requests per period")
    p.add_argument("--period", type=float, default=10.0, help="budget period, s")
    p.add_argument("--top-k", type=int, default=3, help="peer keyframes searched")
    args = p.parse_args(argv)
    wire_sizes()
    if args.bag:
        fleet_run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
