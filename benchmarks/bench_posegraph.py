"""iSAM2 cost of the pose graph: milliseconds per keyframe update as the graph grows to N nodes.

Drives the demo world (seed 8 by default) for ``--nodes`` frames (160 a lap) with the demo's
drifting odometry and a graph node at every frame (a keyframe). A loop every ``--loop-every``
revisiting frames gets its pose from ground truth plus noise (``posegraph.simulate``: a benchmark
helper, never the real pipeline); ``--false-fraction`` adds injected false loops. Odometry is
fed as the node feeds it and every ``update()`` that had new factors is timed (wall and CPU
clock). Prints the update time per keyframe (mean, median, 95th percentile, max) over the whole
run and over the last 10 % of the nodes, and the ATE RMSE before / after.

    python benchmarks/bench_posegraph.py --nodes 1000
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from pair_vpr_ros.demo.camera import Camera, camera_to_base
from pair_vpr_ros.demo.odometry import drifting_odometry
from pair_vpr_ros.demo.world import generate_world
from pair_vpr_ros.offline.report.trajectories import Trajectory, trajectory_errors
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.graph import PoseGraph
from pair_vpr_ros.posegraph.simulate import false_loops, ground_truth_loops
from pair_vpr_ros.posegraph.transforms import planar_pose7


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--nodes", type=int, default=1000, help="graph nodes wanted (%(default)s)")
    p.add_argument("--seed", type=int, default=8, help="demo world seed (%(default)s)")
    p.add_argument("--loop-every", type=int, default=2, help="a loop every K revisit frames")
    p.add_argument("--false-fraction", type=float, default=0.0, help="injected false loops")
    p.add_argument("--loop-iterations", type=int, default=PoseGraphConfig.loop_iterations,
                   help="extra iSAM2 iterations after a loop (%(default)s)")  # fmt: skip
    p.add_argument("--relinearize-threshold", type=float,
                   default=PoseGraphConfig.relinearize_threshold,
                   help="iSAM2 relinearisation threshold (%(default)s)")  # fmt: skip
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    config = PoseGraphConfig(
        camera_to_base=camera_to_base(Camera()), loop_iterations=args.loop_iterations,
        node_spacing_m=0.5,
        relinearize_threshold=args.relinearize_threshold,
    )  # fmt: skip
    # Frames ~0.9 m apart as in the demo (160 a lap), a node at every frame: nodes = keyframes.
    laps = max(3, round(args.nodes / 160))
    world = generate_world(args.seed, frames=args.nodes, laps=laps)
    stamps = world.stamps
    truth = np.array([planar_pose7(*p) for p in world.poses])
    odometry = np.array([
        planar_pose7(*p) for p in drifting_odometry(world.poses, world.config.rate_hz, args.seed)
    ])  # fmt: skip
    rng = np.random.default_rng([args.seed, 5])
    pairs = [(stamps[i], stamps[j]) for i, j in world.revisit_pairs()][:: args.loop_every]
    loops = ground_truth_loops(stamps, truth, pairs, rng, camera_to_base=config.camera_to_base)
    loops += false_loops(stamps, truth, int(args.false_fraction * len(loops)), rng,
                         camera_to_base=config.camera_to_base)  # fmt: skip
    loops.sort(key=lambda lp: lp.query_stamp)
    graph, times, sizes, k = PoseGraph(config), [], [], 0
    for stamp, pose in zip(stamps, odometry, strict=True):
        graph.add_odometry(float(stamp), tuple(pose))
        while k < len(loops) and loops[k].query_stamp <= stamp:
            graph.add_loop(loops[k])
            k += 1
        start, cpu = time.perf_counter(), time.process_time()
        if graph.update():
            times.append((time.perf_counter() - start, time.process_time() - cpu))
            sizes.append(len(graph.nodes))
    graph.finish()
    both, sizes = np.array(times) * 1e3, np.array(sizes)
    false = int(args.false_fraction * 100)
    print(f"world seed {args.seed}: {world.num_frames} frames, {laps} laps, {len(graph.nodes)} "
          f"nodes, {graph.counts.loops_added} loops ({false} % false)")  # fmt: skip
    last = sizes >= 0.9 * sizes[-1]
    for clock, column in (("wall", 0), ("CPU", 1)):
        for name, sample in (("all", both[:, column]), ("last 10 %", both[last, column])):
            print(f"iSAM2 update per keyframe ({clock} time, {name} nodes): mean "
                  f"{sample.mean():.2f} ms, median {np.median(sample):.2f} ms, p95 "
                  f"{np.percentile(sample, 95):.2f} ms, max {sample.max():.2f} ms "
                  f"({len(sample)} updates)")  # fmt: skip
    gt = Trajectory(stamps, truth)
    for name, poses in (("odometry", graph.odometry_poses()),
                        ("optimised", graph.optimised_poses())):  # fmt: skip
        errors = trajectory_errors(Trajectory(graph.node_stamps(), poses), gt)
        print(f"ATE RMSE {name}: {errors.ate_rmse:.3f} m")
    return 0


if __name__ == "__main__":
    sys.exit(main())
