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
import sys
from pathlib import Path
from typing import Any

from pair_vpr_ros.cli import float_flag, nonnegative_int, positive_float, run_cli
from pair_vpr_ros.errors import UsageError
from pair_vpr_ros.offline.posegraph.fleet import fleet_main
from pair_vpr_ros.offline.posegraph.single import run_posegraph
from pair_vpr_ros.offline.report.folder import check_writable
from pair_vpr_ros.params.file import read_params_file
from pair_vpr_ros.params.posegraph import NODE_NAME, PARAMS, posegraph_config
from pair_vpr_ros.posegraph.config import KERNELS, PoseGraphConfig

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
    check_writable(Path(args.out), "--out")  # before the work, which a bad --out would lose
    if args.trajectory is not None:
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
