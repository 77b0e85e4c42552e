"""`pairvpr-posegraph`: odometry from a bag + the loops of a replay -> optimised trajectory.

Feeds the odometry and the loops through the same ``PoseGraph`` the ``posegraph_node`` runs, in
stamp order as the node would see them (a loop is added once the odometry has reached its query
stamp), then writes into ``--out``:

``odometry.tum``, ``optimised.tum`` (and ``ground_truth.tum`` with ``--gt-topic``)
    the graph nodes' odometry and optimised base poses, TUM format (``stamp x y z qx qy qz qw``);
``posegraph.json``
    what went in, what was skipped and why, and the ATE / RPE of odometry and optimised
    trajectory against ground truth (``evo``: SE(3) alignment, RMSE);
``posegraph.png``
    top view of ground truth, odometry and optimised trajectory with the loops drawn.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.cli import float_flag, nonnegative_int, positive_float, run_cli
from pair_vpr_ros.errors import ConfigError, PoseGraphError, UsageError
from pair_vpr_ros.loop_factor import LoopFactor
from pair_vpr_ros.offline import bag_io
from pair_vpr_ros.offline.loop_io import read_loops
from pair_vpr_ros.offline.trajectories import (
    Trajectory,
    plot_trajectories,
    trajectory_errors,
    write_tum,
)
from pair_vpr_ros.params import read_params_file
from pair_vpr_ros.posegraph.graph import KERNELS, PoseGraph, PoseGraphConfig
from pair_vpr_ros.posegraph.params import NODE_NAME, PARAMS, posegraph_config
from pair_vpr_ros.posegraph.simulate import false_loops


@dataclass
class PoseGraphSummary:
    """What one run did; ``errors`` holds ATE / RPE (m) when there is ground truth."""

    odometry_messages: int = 0
    nodes: int = 0
    loops_source: str = ""  # what the loops file held (loop_io.LoopSource.line)
    loops_read: int = 0  # loops with a relative pose
    loops_injected_false: int = 0
    loops_added: int = 0
    # Loops whose residual is above the chi-square 99 % bound at the end: the robust kernel has
    # down-weighted them (false loops, and true ones whose covariance is too confident).
    loop_outliers: int = 0
    injected_false_outliers: int = 0
    odometry_gaps: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    update_ms_mean: float = 0.0
    update_ms_max: float = 0.0
    errors: dict[str, Any] = field(default_factory=dict)  # {"odometry": ..., "optimised": ...}
    config: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    out_dir: str = ""

    def ate_line(self) -> str | None:
        """``drift (ATE RMSE) odometry 3.41 m -> optimised 0.32 m (0.09x)``, or None."""
        if "odometry" not in self.errors or "optimised" not in self.errors:
            return None
        before = self.errors["odometry"]["ate_rmse"]
        after = self.errors["optimised"]["ate_rmse"]
        ratio = after / before if before > 0 else float("nan")
        return (
            f"drift (ATE RMSE) odometry {before:.3f} m -> optimised {after:.3f} m ({ratio:.2f}x)"
        )


def optimise(
    odometry: Trajectory, loops: list[LoopFactor], config: PoseGraphConfig | None = None
) -> tuple[PoseGraph, np.ndarray]:
    """Feed ``odometry`` and ``loops`` in stamp order into a ``PoseGraph`` (updated after each
    odometry message, as the node does); returns the graph and the update times ``[U]`` s."""
    graph = PoseGraph(config)
    order = sorted(loops, key=lambda lp: lp.query_stamp)
    times = []
    k = 0
    for stamp, pose in zip(odometry.stamps, odometry.poses, strict=True):
        graph.add_odometry(float(stamp), tuple(pose))
        while k < len(order) and order[k].query_stamp <= stamp:
            graph.add_loop(order[k])
            k += 1
        start = time.perf_counter()
        if graph.update():
            times.append(time.perf_counter() - start)
    for loop in order[k:]:
        graph.add_loop(loop)
    graph.finish()
    return graph, np.asarray(times, dtype=np.float64)


def read_track(reader: Any, topic: str, what: str, summary: PoseGraphSummary) -> Trajectory:
    """The poses of ``topic`` as a trajectory; a topic without poses is a ``PoseGraphError``.
    Poses with NaN / inf values (left out by ``read_poses``) are counted in ``summary``."""
    track, error = bag_io.read_poses(reader, bag_io.choose_pose_topic(reader, topic))
    if error is not None:
        summary.warnings.append(error)
    if track.rejected:
        key = f"{what}: pose has NaN or infinite values"
        summary.skipped[key] = summary.skipped.get(key, 0) + track.rejected
    if len(track) == 0:
        raise PoseGraphError(
            f"{what} topic {topic} has no messages" + (f" ({error})" if error else "")
        )
    stamps, poses = track.items()
    return Trajectory(np.asarray(stamps, dtype=np.float64), np.asarray(poses, dtype=np.float64))


def _graph_trajectories(graph: PoseGraph) -> tuple[Trajectory, Trajectory]:
    stamps = graph.node_stamps()
    return Trajectory(stamps, graph.odometry_poses()), Trajectory(stamps, graph.optimised_poses())


def run_posegraph(
    bag: str | Path,
    loops_path: str | Path,
    out_dir: str | Path = "posegraph_out",
    odom_topic: str = "/odom",
    gt_topic: str | None = None,
    config: PoseGraphConfig | None = None,
    false_loop_fraction: float = 0.0,
    seed: int = 0,
) -> PoseGraphSummary:
    """Odometry of ``odom_topic`` in ``bag`` + the loops at ``loops_path`` (``loop_io``) -> files
    in ``out_dir`` (see the module docstring). ``false_loop_fraction`` adds that many wrong loops
    per real one (seeded; needs ``gt_topic``) to test robustness. Raises ``PairVPRError``
    subclasses for unusable input."""
    config = config or PoseGraphConfig()
    config.validate()
    if not 0.0 <= false_loop_fraction <= 10.0:
        raise ConfigError(f"false-loop fraction {false_loop_fraction} must be within 0-10")
    if false_loop_fraction > 0 and gt_topic is None:
        raise ConfigError("injecting false loops needs ground truth: pass --gt-topic")
    summary = PoseGraphSummary(config=asdict(config))
    with bag_io.open_bag(bag) as reader:
        odometry = read_track(reader, odom_topic, "odometry", summary)
        truth = read_track(reader, gt_topic, "ground-truth", summary) if gt_topic else None
    source = read_loops(loops_path)
    unusable = summary.skipped.get("odometry: pose has NaN or infinite values", 0)
    summary.odometry_messages, summary.loops_read = len(odometry) + unusable, len(source.factors)
    summary.loops_source = source.line()
    if not source.factors:
        summary.warnings.append(
            f"no loop closure with a relative pose in {loops_path} ({source.line()}): the "
            "optimised trajectory is the odometry"
        )
    injected: list[LoopFactor] = []
    if truth is not None and false_loop_fraction > 0:
        count = int(round(false_loop_fraction * len(source.factors)))
        injected = false_loops(truth.stamps, truth.poses, count, np.random.default_rng(seed),
                               camera_to_base=config.camera_to_base)  # fmt: skip
    graph, times = optimise(odometry, source.factors + injected, config)
    _summarise(summary, graph, times, injected)
    _write_outputs(Path(out_dir), summary, graph, truth)
    return summary


def _write_outputs(
    out: Path, summary: PoseGraphSummary, graph: PoseGraph, truth: Trajectory | None
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    summary.out_dir = str(out)
    before, after = _graph_trajectories(graph)
    write_tum(out / "odometry.tum", before)
    write_tum(out / "optimised.tum", after)
    (out / "ground_truth.tum").unlink(missing_ok=True)  # an earlier run's would mislead
    if truth is not None:
        write_tum(out / "ground_truth.tum", truth)
        for name, estimate in (("odometry", before), ("optimised", after)):
            summary.errors[name] = trajectory_errors(estimate, truth).to_dict()
    plot_trajectories(out / "posegraph.png", truth, before, after, graph.loop_segments(),
                      graph.loop_inliers(), summary.ate_line() or "")  # fmt: skip
    (out / "posegraph.json").write_text(json.dumps(asdict(summary), indent=1) + "\n")


def _summarise(
    summary: PoseGraphSummary, graph: PoseGraph, times: np.ndarray, injected: list[LoopFactor]
) -> None:
    counts = graph.counts
    inliers = graph.loop_inliers()
    false = np.array([any(e.factor is f for f in injected) for e in graph.loops], dtype=bool)
    summary.loops_injected_false = len(injected)
    summary.nodes = counts.nodes
    summary.loops_added = counts.loops_added
    summary.loop_outliers = int((~inliers).sum())
    summary.injected_false_outliers = int((~inliers & false).sum())
    summary.odometry_gaps = counts.odometry_gaps
    for reason, n in counts.skipped.items():  # after the poses read_poses left out
        summary.skipped[reason] = summary.skipped.get(reason, 0) + n
    if len(times):
        summary.update_ms_mean = float(times.mean() * 1e3)
        summary.update_ms_max = float(times.max() * 1e3)


FRACTION = float_flag("a number from 0 to 10", lambda v: 0.0 <= v <= 10.0)


def _camera_pose(text: str) -> tuple[float, ...]:
    values = tuple(float(v) for v in text.replace(",", " ").split())
    if len(values) != 7:
        raise argparse.ArgumentTypeError(
            f"expected 7 numbers 'x y z qx qy qz qw', got {len(values)} in {text!r}"
        )
    return values


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pairvpr-posegraph",
        description="Correct a bag's odometry with the loop closures of a pairvpr-bag-replay run: "
        "GTSAM pose graph (iSAM2, robust loop factors), TUM trajectories before/after, ATE/RPE "
        "against ground truth (evo) and a picture.",
    )
    p.add_argument("bag", nargs="?",
                   help="bag with the odometry (rosbag2 folder, .mcap, .db3 or ROS 1 .bag) of one "
                   "robot; several robot-sessions: --trajectory instead")  # fmt: skip
    p.add_argument(
        "--trajectory", nargs=3, action="append", metavar=("ROBOT", "SESSION", "BAG"),
        help="one robot-session and the bag with its odometry (repeat for each; the first is "
        "the map frame): each gets ROBOT/SESSION/optimised.tum in --out, in the first one's frame",
    )  # fmt: skip
    p.add_argument(
        "--loops", metavar="PATH", action="append",
        help="the loops: a pairvpr-bag-replay --out folder, its loops.json, or the bag it wrote "
        "with --write-bag (with --trajectory: repeat for several robots' replays; else the last "
        "one counts)",
    )  # fmt: skip
    p.add_argument(
        "--loops-of", nargs=3, action="append", metavar=("ROBOT", "SESSION", "PATH"),
        help="with --trajectory: the loops of ROBOT's SESSION replay; loop ends that name no "
        "robot and session (a replay without --robot-id) are that robot-session's",
    )  # fmt: skip
    p.add_argument("--out", metavar="DIR", default="posegraph_out",
                   help="output folder (default: %(default)s)")  # fmt: skip
    p.add_argument(
        "--odom-topic", default="/odom",
        help="nav_msgs/Odometry (or PoseStamped) topic to correct (default: %(default)s)",
    )  # fmt: skip
    p.add_argument("--gt-topic", help="ground-truth pose topic for ATE / RPE (default: none)")
    p.add_argument(
        "--params-file", type=Path,
        help="graph settings from a posegraph_node parameter file (config/posegraph_node.yaml); "
        "the flags below override it",
    )  # fmt: skip
    p.add_argument(
        "--camera-to-base", type=_camera_pose, metavar="'X Y Z QX QY QZ QW'",
        help="pose of the loops' camera frame in the odometry's base frame (default: identity); "
        "the demo's: '0 0 1.6 -0.5 0.5 -0.5 0.5'",
    )  # fmt: skip
    p.add_argument("--kernel", choices=KERNELS, help="robust kernel on loop factors")
    p.add_argument("--node-spacing", type=positive_float, metavar="M",
                   help="metres of travel between graph nodes")  # fmt: skip
    p.add_argument(
        "--inject-false-loops", type=FRACTION, default=0.0, metavar="FRACTION",
        help="add FRACTION x (real loops) wrong loops with plausible poses, to test robustness "
        "(needs --gt-topic; default: 0)",
    )  # fmt: skip
    p.add_argument("--seed", type=nonnegative_int, default=0,
                   help="seed of --inject-false-loops (default: 0)")  # fmt: skip
    return p


def _config(args: argparse.Namespace) -> PoseGraphConfig:
    values: dict[str, Any] = {}
    if args.params_file is not None:
        values = read_params_file(args.params_file, NODE_NAME, PARAMS)
        if values.get("prior_map_dirs"):  # the node's; offline every session is a bag
            print("warning: prior_map_dirs is posegraph_node's, not read here: give each "
                  "session as --trajectory ROBOT SESSION BAG", file=sys.stderr)  # fmt: skip
    for name, value in (("camera_to_base", args.camera_to_base), ("loop_kernel", args.kernel),
                        ("node_spacing_m", args.node_spacing)):  # fmt: skip
        if value is not None:
            values[name] = value
    return posegraph_config(values)


def main(argv: list[str] | None = None) -> int:
    """Exit codes: ``pair_vpr_ros.cli`` (0 done, 1 error or bad input, 2 usage, 130 Ctrl-C)."""
    return run_cli(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> None:
    if (args.bag is None) == (args.trajectory is None):
        raise UsageError("give one robot's BAG or several --trajectory ROBOT SESSION BAG")
    if args.trajectory is not None:
        from pair_vpr_ros.offline.posegraph_fleet import fleet_main

        return fleet_main(args, _config(args))
    if args.loops is None or args.loops_of is not None:
        raise UsageError("one robot's BAG needs --loops PATH (--loops-of goes with --trajectory)")
    summary = run_posegraph(
        args.bag, args.loops[-1], args.out, odom_topic=args.odom_topic, gt_topic=args.gt_topic,
        config=_config(args), false_loop_fraction=args.inject_false_loops, seed=args.seed,
    )  # fmt: skip
    for warning in summary.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    skipped = sum(summary.skipped.values())
    print(f"loops: {summary.loops_source}")
    print(
        f"{summary.nodes} nodes from {summary.odometry_messages} odometry messages, "
        f"{summary.loops_added} loops in the graph ({summary.loop_outliers} outliers, "
        f"down-weighted by the robust kernel), {skipped} inputs skipped"
        + (f": {summary.skipped}" if skipped else "")
    )
    if summary.loops_injected_false:
        print(
            f"injected {summary.loops_injected_false} false loops: "
            f"{summary.injected_false_outliers} among the outliers"
        )
    line = summary.ate_line()
    if line:
        print(line)
    print(f"outputs in {summary.out_dir}: odometry.tum, optimised.tum, posegraph.json/.png")


if __name__ == "__main__":
    sys.exit(main())
