"""The multi-robot pose graph on the demo fleet's bags, with loops made up from ground truth.

Reads each robot-session's ``/odom`` and ``/ground_truth`` from ``pairvpr-make-demo-bag --fleet``
bags (``fleet.json``), makes a loop from every ``--loop-every``-th frame to the nearest frame of
any earlier-recorded robot-session (or its own drive, 20 s back or more) within ``--radius`` m,
its pose from ground truth plus noise (``posegraph.simulate``: a benchmark helper, never the real
pipeline), adds ``--false-fraction`` x false loops between robots (pairs > 30 m apart claiming a
plausible revisit), and runs ``optimise_fleet``. Prints per robot-session the ATE (SE(3)-aligned)
of the odometry and of the optimised trajectory, and the ATE after the first robot's alignment
only (all in one frame), plus how many false loops ended as outliers. This isolates the graph
from the loop detector: ``make demo-fleet`` measures both together.

    python benchmarks/bench_posegraph_fleet.py demo_out/fleet --false-fraction 0.1
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from pair_vpr_ros.demo.camera import Camera, camera_to_base
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.posegraph.fleet import optimise_fleet
from pair_vpr_ros.offline.posegraph.single import PoseGraphSummary, read_track
from pair_vpr_ros.offline.report.trajectories import (
    Trajectory,
    reference_alignment,
    trajectory_errors,
)
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.simulate import make_factor, trajectory_loops
from pair_vpr_ros.posegraph.transforms import pose3


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("fleet", type=Path, help="folder with fleet.json and the bags")
    p.add_argument("--loop-every", type=int, default=3, help="a loop every K frames")
    p.add_argument("--radius", type=float, default=6.0, help="loop radius, m (%(default)s)")
    p.add_argument("--false-fraction", type=float, default=0.0, help="false loops between robots")
    p.add_argument("--join-min-loops", type=int, default=PoseGraphConfig.join_min_loops)
    p.add_argument("--seed", type=int, default=0, help="noise seed (%(default)s)")
    return p.parse_args(argv)


def read(fleet: Path) -> dict:
    drives = {}
    for entry in json.loads((fleet / "fleet.json").read_text())["drives"]:
        scratch = PoseGraphSummary()
        with open_bag(fleet / entry["bag"]) as reader:
            odom = read_track(reader, "/odom", "odometry", scratch)
            truth = read_track(reader, "/ground_truth", "ground truth", scratch)
        drives[(entry["robot"], entry["session"])] = (odom, truth)
    return drives


def make_loops(drives: dict, args: argparse.Namespace, rng: np.random.Generator) -> tuple:
    camera = camera_to_base(Camera())
    ids, loops, false = list(drives), [], []
    for qi, q in enumerate(ids):
        qt = drives[q][1]
        for i in range(0, len(qt), args.loop_every):
            for m in ids[: qi + 1]:
                mt = drives[m][1]
                d = np.linalg.norm(mt.poses[:, :2] - qt.poses[i, :2], axis=1)
                if m == q:
                    d[mt.stamps > qt.stamps[i] - 20.0] = np.inf
                j = int(np.argmin(d))
                if d[j] <= args.radius:
                    loops += trajectory_loops((qt.stamps, qt.poses), (mt.stamps, mt.poses),
                                              [(qt.stamps[i], mt.stamps[j])], rng,
                                              camera_to_base=camera, query=q, match=m)  # fmt: skip
                    break
    between = [lp for lp in loops if lp.query_robot != lp.match_robot]
    for _ in range(round(args.false_fraction * len(between))):
        a, b = rng.choice(len(ids), 2, replace=False)
        qa, mb = drives[ids[a]][1], drives[ids[b]][1]
        for _ in range(1000):
            i, j = rng.integers(len(qa)), rng.integers(len(mb))
            if np.linalg.norm(qa.poses[i, :2] - mb.poses[j, :2]) > 30.0:
                break
        claimed = pose3((rng.uniform(-2, 2), 0.0, rng.uniform(-2, 2), 0, 0, 0, 1))
        f = make_factor(qa.stamps[i], mb.stamps[j], claimed, np.diag([0.01] * 3 + [3e-4] * 3))
        from dataclasses import replace

        false.append(replace(f, query_robot=ids[a][0], query_session=ids[a][1],
                             match_robot=ids[b][0], match_session=ids[b][1]))  # fmt: skip
    return loops, false


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    drives = read(args.fleet)
    loops, false = make_loops(drives, args, np.random.default_rng(args.seed))
    config = PoseGraphConfig(camera_to_base=camera_to_base(Camera()),
                             join_min_loops=args.join_min_loops)  # fmt: skip
    start = time.perf_counter()
    graph = optimise_fleet({k: v[0] for k, v in drives.items()}, loops + false, config)
    seconds = time.perf_counter() - start
    inliers = graph.loop_inliers()
    injected = np.array([any(e.factor is f for f in false) for e in graph.loops], dtype=bool)
    between = sum((lp.query_robot, lp.query_session) != (lp.match_robot, lp.match_session)
                  for lp in loops)  # fmt: skip
    caught = int((~inliers & injected).sum())
    print(
        f"{len(loops)} loops from ground truth ({between} between robot-sessions), "
        f"{len(false)} false between robots: {caught} of them outliers, "
        f"{int((~inliers).sum()) - caught} true loops outliers; {seconds:.1f} s"
    )
    ref = next(iter(drives))
    after = {k: Trajectory(graph.node_stamps(k), graph.optimised_poses(k)) for k in drives}
    to_truth = reference_alignment(after[ref], drives[ref][1])
    for k, (_, truth) in drives.items():
        before = Trajectory(graph.node_stamps(k), graph.odometry_poses(k))
        b = trajectory_errors(before, truth).ate_rmse
        a = trajectory_errors(after[k], truth).ate_rmse
        one = trajectory_errors(after[k], truth, alignment=to_truth).ate_rmse
        print(
            f"{'/'.join(k)}: joined {graph.joined(k)}, ATE odometry {b:.3f} m -> optimised "
            f"{a:.3f} m ({a / b:.2f}x), in the first one's frame {one:.3f} m"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
