"""`pairvpr-bag-replay`: the command line of ``offline.replay.replay_bag``.

With only a bag (``PAIRVPR_WEIGHTS=... pairvpr-bag-replay bag.mcap``) the weights are found as
``weights.resolve_weights`` says, the topics as ``replay_bag`` picks them, and every output goes
to ``replay_out/``. Exit codes: ``pair_vpr_ros.cli``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from pair_vpr_ros.cli import (
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_OK,
    finite_float,
    float_flag,
    positive_int,
    run_cli,
)
from pair_vpr_ros.geometry.features import KINDS
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.identity import DEFAULT_ROBOT, RULE, name_problem
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.offline.bags.opening import check_bag_path
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.printing import print_results
from pair_vpr_ros.offline.replay.rig import camera_options
from pair_vpr_ros.offline.replay.run import replay_bag
from pair_vpr_ros.params.check import flag_help, flag_type
from pair_vpr_ros.params.configs import detector_config, geometry_config, index_config
from pair_vpr_ros.params.file import read_params_file
from pair_vpr_ros.params.table import SPECS
from pair_vpr_ros.weights import resolve_weights

NONE = "none"  # --pose-topic none / --map-dir none / --openvino-cache-dir none
# Flags that mirror node parameters (default: the --params-file's value, else the parameter's).
RUNTIME = (
    "precision",
    "backend",
    "openvino_cache_dir",
    "openvino_calibration",
    "openvino_calibration_topic",
    "num_threads",
)
# ... the map: its index and how it stores dense tokens
INDEX = (
    "index", "milvus_uri", "milvus_collection", "milvus_index", "milvus_consistency",
    "dense_codec",
)  # fmt: skip
DEPTH_TOLERANCE = float_flag("a number of seconds in [0, 1]", lambda v: 0 <= v <= 1)

POSITIVE_METRES = float_flag("a finite number of metres > 0", lambda v: v > 0)
TARGET = float_flag("a precision in (0, 1]", lambda v: 0 < v <= 1)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pairvpr-bag-replay",
        description="Replay a rosbag's camera topic through the Pair-VPR loop-closure pipeline "
        "(the same one vpr_node runs) and write loops, the place map and an evaluation report.",
    )
    p.add_argument("bag", help="rosbag2 folder (mcap or sqlite3), .mcap / .db3 file or ROS 1 .bag")
    p.add_argument(
        "--weights",
        metavar="PATH",
        help="Pair-VPR checkpoint (.pth); default: $PAIRVPR_WEIGHTS, else 'weights' in "
        "--params-file, else the one .pth in $XDG_DATA_HOME/pair_vpr_ros/ "
        "(~/.local/share/pair_vpr_ros/)",
    )
    p.add_argument(
        "--out", metavar="DIR", default="replay_out", help="output folder (default: %(default)s)"
    )
    p.add_argument(
        "--topic",
        action="append",
        help="image topic (Image or CompressedImage); needed when the bag has several. Repeat "
        "it for a rig of cameras (one map, loops in the base frame; docs/rig.md): each camera "
        "takes its namespace's camera_info and depth topics and its extrinsic from /tf_static",
    )
    p.add_argument(
        "--rig",
        metavar="FILE",
        help="a rig file (YAML; docs/rig.md): several cameras, each with its image, camera_info "
        "and depth (or right image) topics and camera_to_base, the stamp tolerance of a rig "
        "keyframe and the base frame; instead of --topic",
    )
    p.add_argument(
        "--pose-topic",
        help="Odometry / PoseStamped / PoseWithCovarianceStamped topic whose poses are attached "
        "to keyframes and saved in the map, like the node's pose_topic (default: the bag's only "
        "pose topic besides --gt-topic; 'none' to attach none)",
    )
    p.add_argument(
        "--gt-topic",
        help="pose topic of ground truth for precision / recall and the plots, kept apart from "
        "--pose-topic because odometry drifts (default: the --pose-topic one; 'none': no "
        "evaluation)",
    )
    p.add_argument(
        "--gt-radius",
        type=POSITIVE_METRES,
        default=10.0,
        metavar="M",
        help="a loop is true when its keyframes lie within M metres (default: %(default)s)",
    )
    p.add_argument(
        "--threshold",
        type=finite_float,
        help="acceptance threshold of the re-rank score (default: detector's)",
    )
    p.add_argument(
        "--params-file",
        type=Path,
        help="take the detector settings from a vpr_node parameter file "
        "(e.g. config/vpr_node.yaml); --threshold, --top-k, --global-weight and "
        "--rerank-budget-ms still override",
    )
    p.add_argument(
        "--top-k",
        type=positive_int,
        help="candidates re-ranked per keyframe (default: detector's)",
    )
    p.add_argument(
        "--global-weight",
        type=flag_type("global_weight"),
        metavar="W",
        help=flag_help("global_weight") + " (default: --params-file's, else 0)",
    )
    p.add_argument(
        "--rerank-budget-ms",
        type=flag_type("rerank_budget_ms"),
        metavar="MS",
        help=flag_help("rerank_budget_ms") + " (default: --params-file's, else 0)",
    )
    p.add_argument(
        "--device",
        default="cpu",
        help="torch device: cpu, cuda, cuda:1, auto (default: %(default)s)",
    )
    for name in ("precision", "backend"):
        default = SPECS[name].default
        p.add_argument(
            f"--{name}",
            choices=SPECS[name].choices,
            help=flag_help(name) + f" (default: --params-file's, else {default})",
        )
    p.add_argument(
        "--threads", dest="num_threads", metavar="N", type=flag_type("num_threads", auto=0),
        help=flag_help("num_threads") + "; auto = 0 (default: --params-file's, else auto)",
    )  # fmt: skip
    p.add_argument(
        "--openvino-cache-dir",
        metavar="DIR",
        help=flag_help("openvino_cache_dir") + " or none (default: --params-file's, else auto)",
    )
    for name, var in (("openvino_calibration", "PATH"), ("openvino_calibration_topic", "TOPIC")):
        p.add_argument(
            f"--{name.replace('_', '-')}",
            metavar=var,
            help=flag_help(name) + " (default: --params-file's, else '')",
        )
    for name in INDEX:
        spec = SPECS[name]
        p.add_argument(
            f"--{name.replace('_', '-')}",
            choices=spec.choices or None,
            metavar=None if spec.choices else "TEXT",
            help=flag_help(name) + f" (default: --params-file's, else {spec.default!r})",
        )
    p.add_argument(
        "--batch-size",
        type=positive_int,
        default=8,
        help="frames encoded per batch (default: %(default)s)",
    )
    p.add_argument(
        "--write-bag",
        action="store_true",
        help="also write OUT/bag: images and loop-closure topics",
    )
    p.add_argument(
        "--map-dir",
        metavar="DIR",
        help="where to save the place map (default: OUT/map; 'none' to not save it); a saved "
        "map already there is refused unless --overwrite",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a saved place map at the map folder (else the replay refuses to start)",
    )
    p.add_argument(
        "--depth-topic",
        help="aligned depth image topic (16UC1 mm / 32FC1 m) for metric relative poses "
        "(default: the bag's only depth image topic; 'none' for monocular poses)",
    )
    p.add_argument(
        "--camera-info-topic",
        help="sensor_msgs/CameraInfo topic of the camera (default: the bag's only one; 'none': "
        "no intrinsics, so no relative poses)",
    )
    p.add_argument(
        "--right-topic",
        help="stereo: the right camera's rectified image topic; keyframes without depth get it "
        "from StereoSGBM on the pair (needs --camera-info-topic and --right-camera-info-topic)",
    )
    p.add_argument(
        "--right-camera-info-topic",
        help="stereo: the right camera's sensor_msgs/CameraInfo (its P gives the baseline)",
    )
    p.add_argument(
        "--depth-tolerance",
        type=DEPTH_TOLERANCE,
        default=0.02,
        metavar="S",
        help="largest stamp gap between an image and its depth image (default: %(default)s s)",
    )
    p.add_argument(
        "--features",
        choices=KINDS,
        default="sift",
        help="keypoints for relative poses: sift (accurate) or orb (cheaper) (default: sift)",
    )
    p.add_argument("--max-frames", type=positive_int, help="stop after this many image messages")
    p.add_argument(
        "--max-image-pixels",
        type=positive_int,
        metavar="N",
        help="skip (and count) images larger than N pixels, width x height, before decoding "
        f"(default: --params-file's max_image_pixels, else {MAX_PIXELS:,})",
    )
    p.add_argument(
        "--robot-id", metavar="NAME", type=identity_flag("robot_id"),
        help=f"robot of every keyframe and loop (default: --params-file's robot_id, else "
        f"'{DEFAULT_ROBOT}'); {RULE}",
    )  # fmt: skip
    p.add_argument(
        "--session-id", metavar="NAME", type=identity_flag("session_id"),
        help="session of every keyframe and loop (default: --params-file's session_id, else the "
        f"start time, UTC, YYYYMMDDTHHMMSSZ); {RULE}",
    )  # fmt: skip
    p.add_argument(
        "--prior-map", metavar="DIR", action="append", default=[],
        help="a saved place map loaded read-only and searched with the live map (repeat for "
        "several; added to --params-file's prior_map_dirs); never written",
    )  # fmt: skip
    p.add_argument(
        "--no-report",
        action="store_true",
        help="do not write OUT/report/ (pages that show every keyframe's candidates, decision "
        "and loop image; open OUT/report/index.html in a browser)",
    )
    p.add_argument(
        "--target-precision",
        type=TARGET,
        default=0.99,
        metavar="P",
        help="with ground truth, OUT/suggested_params.yaml holds the score_threshold (and "
        "global_floor) whose loops reach this precision on the bag (default: %(default)s)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def identity_flag(name: str):
    """argparse type of --robot-id / --session-id: the identity rule (identity.py)."""

    def parse(text: str) -> str:
        problem = name_problem(name, text)
        if problem:
            raise argparse.ArgumentTypeError(problem)
        return text

    return parse


def main(argv: list[str] | None = None) -> int:
    """Exit codes: `pair_vpr_ros.cli`; a replay stopped part-way by a read error is 1, by
    Ctrl-C 130, with what was processed before written either way."""
    return run_cli(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> int:
    overrides = {
        "score_threshold": args.threshold,
        "top_k": args.top_k,
        "global_weight": args.global_weight,
        "rerank_budget_ms": args.rerank_budget_ms,
    }
    overrides = {k: v for k, v in overrides.items() if v is not None}
    max_pixels, runtime = MAX_PIXELS, {n: SPECS[n].default for n in RUNTIME}
    fleet = {name: SPECS[name].default for name in ("robot_id", "session_id", "prior_map_dirs")}
    index = {n: SPECS[n].default for n in INDEX}
    values = None
    if args.params_file is not None:
        values = read_params_file(args.params_file)
        config = detector_config(values).updated(**overrides)
        max_pixels = values["max_image_pixels"]
        runtime = {name: values[name] for name in runtime}
        fleet = {name: values[name] for name in fleet}
        index = {name: values[name] for name in INDEX}
    else:
        config = DetectorConfig(**overrides)
    index.update({n: getattr(args, n) for n in INDEX if getattr(args, n) is not None})
    index["milvus_token_env"] = SPECS["milvus_token_env"].default
    if args.openvino_cache_dir == NONE:
        args.openvino_cache_dir = ""
    runtime = {
        name: value if getattr(args, name) is None else getattr(args, name)
        for name, value in runtime.items()
    }
    cameras = camera_options(args)  # one topic, or a rig
    check_bag_path(args.bag)  # a wrong bag path is said before the weights search
    weights = resolve_weights(args.weights, args.params_file)
    options = ReplayOptions(
        **cameras, pose_topic=args.pose_topic, gt_topic=args.gt_topic,
        depth_topic=args.depth_topic, camera_info_topic=args.camera_info_topic,
        right_topic=args.right_topic, right_camera_info_topic=args.right_camera_info_topic,
        gt_radius=args.gt_radius, depth_tolerance=args.depth_tolerance,
        batch_size=args.batch_size, max_frames=args.max_frames,
        max_image_pixels=args.max_image_pixels or max_pixels, device=args.device,
        write_bag=args.write_bag, map_dir=None if args.map_dir == NONE else args.map_dir,
        save_map=args.map_dir != NONE, overwrite=args.overwrite, progress=not args.quiet,
        robot_id=args.robot_id or fleet["robot_id"],
        session_id=args.session_id or fleet["session_id"],
        prior_maps=(*fleet["prior_map_dirs"], *args.prior_map), announce=print,
        index=index_config(index), report=not args.no_report,
        target_precision=args.target_precision, params_values=values, **runtime,
    )  # fmt: skip
    geometry = GeometryConfig(features=args.features)
    if args.params_file is not None:  # depth noise, max depth: the parameter file's
        geometry = replace(geometry_config(values), features=args.features)
    summary = replay_bag(
        args.bag, args.out, options, weights=weights, config=config, geometry=geometry
    )
    print_results(summary)
    print(summary.line())
    if summary.error:
        print(f"error: {summary.error} (what was processed before is written)", file=sys.stderr)
        return EXIT_INTERRUPTED if summary.interrupted else EXIT_ERROR
    return EXIT_OK


if __name__ == "__main__":
    raise SystemExit(main())
