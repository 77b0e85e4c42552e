"""Accuracy of the relative poses of a replay's accepted loops against the demo world's truth.

    python benchmarks/eval_relpose.py OUT/loops.json --seed 7 --frames 600

Each record's stamps give the two frames of the demo world (`generate_world(seed, frames=...)`);
the true T_match_query comes from their camera poses. A loop is true when the two cameras are
within --gt-radius metres (the replay report's rule). Prints, for accepted true loops: how many
got a metric / metric-odometry (monocular, length from odometry) / scale-free pose or none (with
the reasons), median and 90th-percentile rotation error (deg), translation error (m, metric
poses), translation direction error (deg) and, for metric poses, the length error divided by
the covariance's std along the translation (a calibrated covariance gives a median of 0.67).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from pair_vpr_ros.demo import generate_world
from pair_vpr_ros.demo.camera import Camera
from pair_vpr_ros.demo.views import pose_errors, true_relative_pose
from pair_vpr_ros.messages.factor import factor_from_record


def evaluate(records: list[dict], seed: int, frames: int, gt_radius: float) -> dict:
    """loops.json records -> figures (see the module docstring)."""
    world = generate_world(seed, frames=frames)
    cam = Camera(width=world.config.width, height=world.config.height)
    index = {int(ns): i for i, ns in enumerate(world.stamps_ns)}

    def frame(stamp: float) -> int:
        return index[int(round(stamp * 1e9 / 1e6)) * 1_000_000]  # stamps are whole ms here

    status, reasons = Counter(), Counter()
    errors = {"metric": [], "metric-odometry": [], "scale-free": []}
    accepted = [r for r in records if r["accepted"]]
    true = 0
    for r in accepted:
        q, m = frame(r["query_stamp"]), frame(r["match_stamp"])
        if math.dist(world.poses[q, :2], world.poses[m, :2]) > gt_radius:
            continue
        true += 1
        status[r["pose_status"] or "none"] += 1
        factor = factor_from_record(r)
        if factor is None:
            reasons[re.sub(r"\d+(\.\d+)?", "N", r["pose_reason"])] += 1
            continue
        truth = true_relative_pose(world.poses[m], world.poses[q], cam)
        errors[r["pose_status"]].append((*pose_errors(factor.matrix(), truth),
                                         _length_z(factor, truth)))  # fmt: skip
    out = {"accepted": len(accepted), "accepted_true": true, "status": dict(status),
           "no_pose_reasons": dict(reasons)}  # fmt: skip
    for name, errs in errors.items():
        e = np.asarray(errs).reshape(-1, 4)
        if len(e):
            metric = name != "scale-free"
            out[name] = {
                "n": len(e),
                "rotation_deg": _stats(e[:, 0]),
                "translation_m": _stats(e[:, 1]) if metric else None,
                "direction_deg": _stats(e[:, 2]),
                "length_error_over_std": _stats(np.abs(e[:, 3])) if metric else None,
            }
    with_pose = sum(status[k] for k in errors)
    out["with_pose"] = with_pose / true if true else None
    for name in ("metric", "metric-odometry"):
        out[f"{name}_share"] = status[name] / true if true else None
    return out


def _length_z(factor, truth: np.ndarray) -> float:
    """(estimated - true length of t) / the covariance's std along t."""
    t = np.asarray(factor.translation)
    t_hat = t / np.linalg.norm(t)
    std = math.sqrt(float(t_hat @ factor.covariance_matrix()[:3, :3] @ t_hat))
    return (float(np.linalg.norm(t)) - float(np.linalg.norm(truth[:3, 3]))) / std


def _stats(values: np.ndarray) -> dict:
    return {
        "median": float(np.median(values)),
        "p90": float(np.percentile(values, 90)),
        "max": float(np.max(values)),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("loops", type=Path, help="loops.json of a pairvpr-bag-replay run")
    p.add_argument("--seed", type=int, required=True, help="demo world seed of the bag")
    p.add_argument("--frames", type=int, default=480, help="frames of the demo world")
    p.add_argument("--gt-radius", type=float, default=10.0, help="true-loop radius, m")
    args = p.parse_args(argv)
    try:
        records = json.loads(args.loops.read_text())
    except (OSError, json.JSONDecodeError) as err:
        print(f"error: cannot read {args.loops}: {err}", file=sys.stderr)
        return 1
    print(json.dumps(evaluate(records, args.seed, args.frames, args.gt_radius), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
