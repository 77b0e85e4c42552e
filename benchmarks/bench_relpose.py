"""Cost of the relative pose per accepted loop, and of feature extraction per keyframe.

    python benchmarks/bench_relpose.py [--pairs 40] [--threads 2]

Renders revisit pairs of the demo world (seed 8: query on a later lap, match on lap 0, 1-3 m and
10-25 deg apart, other lighting), extracts features of both keyframes (timed: this is paid for
every keyframe) and times `relative_pose` (paid per accepted loop: matching, PnP or essential
matrix, refinement, covariance), with OpenCV limited to --threads threads. Prints median and
90th percentile milliseconds for SIFT and ORB, with depth, monocular, and monocular with the
length from the odometry baselines to the match's neighbours (frames match-2 .. match+2 with
their true poses as odometry; matching and triangulating over them is the extra cost), and the
load average (the figures are only as clean as the machine is idle).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import cv2
import numpy as np

from pair_vpr_ros.demo import generate_world
from pair_vpr_ros.demo.camera import Camera
from pair_vpr_ros.demo.views import camera_model, render_keyframe
from pair_vpr_ros.geometry import PoseConfig, extract_features, relative_pose
from pair_vpr_ros.geometry.features import pack_features
from pair_vpr_ros.geometry.odometry_scale import pick_neighbours


def _odometry(pose: np.ndarray) -> tuple:
    """Demo camera pose (x, y, yaw) -> odometry pose (x, y, z, qx, qy, qz, qw)."""
    x, y, yaw = (float(v) for v in pose)
    return (x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _ms(values: list[float]) -> str:
    return f"median {np.median(values):6.1f} ms, p90 {np.percentile(values, 90):6.1f} ms"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=40, help="revisit pairs to time")
    p.add_argument("--threads", type=int, default=2, help="OpenCV threads (CI has 2 cores)")
    p.add_argument("--repeat", type=int, default=3, help="timings per pair (the best is kept)")
    p.add_argument(
        "--scale-tries",
        type=int,
        default=PoseConfig().scale_tries,
        help="neighbours used for a monocular length (PoseConfig.scale_tries)",
    )
    args = p.parse_args(argv)
    config = PoseConfig(scale_tries=args.scale_tries)
    cv2.setNumThreads(args.threads)
    world = generate_world(8)
    model = camera_model(Camera())
    pairs = world.revisit_pairs()
    pairs = [pairs[i] for i in np.linspace(0, len(pairs) - 1, args.pairs).astype(int)]
    span = config.scale_neighbours
    near = {m: [i for i in range(m - span, m + span + 1) if i != m and 0 <= i < len(world.poses)]
            for _, m in pairs}  # fmt: skip
    wanted = {i for pair in pairs for i in pair} | {i for ids in near.values() for i in ids}
    views = {i: render_keyframe(world, i) for i in sorted(wanted)}
    print(f"{len(pairs)} pairs, {args.threads} OpenCV threads, load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")  # fmt: skip
    for kind in ("sift", "orb"):
        extract, sizes = [], []
        feats = {}
        for i, (rgb, depth) in views.items():
            t0 = time.perf_counter()
            feats[i] = extract_features(rgb, kind, depth=depth, camera=model)
            extract.append((time.perf_counter() - t0) * 1e3)
            sizes.append(len(pack_features(feats[i])))
        print(
            f"{kind}: features per keyframe {_ms(extract)}; {np.median(sizes) / 1024:.1f} KiB "
            f"stored (median, {np.median([len(f) for f in feats.values()]):.0f} keypoints)"
        )
        mono = {
            i: type(f)(f.keypoints, f.descriptors, kind, None, model) for i, f in feats.items()
        }
        for mode in ("depth", "monocular", "odometry"):
            times, status = [], []
            for q, m in pairs:
                fq, fm, neighbours = feats[q], feats[m], []
                if mode != "depth":
                    fq, fm = mono[q], mono[m]
                if mode == "odometry":
                    cands = [(i, float(i), _odometry(world.poses[i])) for i in near[m]]
                    neighbours = pick_neighbours(float(m), _odometry(world.poses[m]), cands,
                                                 mono.get, config)  # fmt: skip
                best = np.inf
                for _ in range(args.repeat):
                    t0 = time.perf_counter()
                    pose = relative_pose(fq, fm, config, neighbours)
                    best = min(best, (time.perf_counter() - t0) * 1e3)
                times.append(best)
                status.append(pose.status or "none")
            done = sum(s != "none" for s in status) / len(status)
            scaled = sum(s == "metric-odometry" for s in status) / len(status)
            extra = f", {scaled:.0%} with a length from odometry" if mode == "odometry" else ""
            print(f"  {mode:9s} relative pose {_ms(times)} ({done:.0%} with a pose{extra})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
