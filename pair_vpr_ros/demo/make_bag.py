"""`pairvpr-make-demo-bag`: write the synthetic loop drive as a rosbag, and/or a place dataset."""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

from pair_vpr_ros.cli import run_cli
from pair_vpr_ros.demo.bag import (
    CAMERA_INFO_TOPIC,
    COMPRESSED_TOPIC,
    DEPTH_TOPIC,
    GROUND_TRUTH_TOPIC,
    IMAGE_TOPIC,
    ODOM_TOPIC,
    write_world_bag,
)
from pair_vpr_ros.demo.dataset import write_place_dataset
from pair_vpr_ros.demo.odometry import OdometryNoise
from pair_vpr_ros.demo.rig import REAR_IMAGE_TOPIC, RIG_REVERSE_LAPS
from pair_vpr_ros.demo.world import WorldConfig, generate_world
from pair_vpr_ros.errors import UsageError


def parse_size(text: str) -> tuple[int, int]:
    """'320x240' -> (320, 240); argparse type."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(
            f"invalid size {text!r}: expected WIDTHxHEIGHT, e.g. 320x240"
        )
    return int(match[1]), int(match[2])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pairvpr-make-demo-bag",
        description=(
            "Render the synthetic loop world (a seeded street grid driven in several laps: "
            "revisits with lateral and heading offsets, day/dusk/overcast light, other parked "
            f"cars) to a rosbag2 MCAP with {IMAGE_TOPIC} (or {COMPRESSED_TOPIC}), "
            f"{CAMERA_INFO_TOPIC}, aligned depth on {DEPTH_TOPIC} (16UC1 mm), drifting "
            f"odometry on {ODOM_TOPIC} and the true poses on {GROUND_TRUTH_TOPIC}; optionally "
            "also write a place-recognition training dataset "
            "(DIR/<place>/<k>.png)."
        ),
    )
    parser.add_argument(
        "out",
        nargs="?",
        type=Path,
        help="output bag: a path ending in .mcap gives one MCAP file, anything else a bag folder",
    )
    parser.add_argument("--seed", type=int, default=7, help="world seed (default: 7)")
    parser.add_argument(
        "--frames",
        type=int,
        default=WorldConfig.frames,
        help=f"camera frames at 10 Hz over all laps (default: {WorldConfig.frames})",
    )
    parser.add_argument(
        "--laps", type=int, default=WorldConfig.laps, help="laps of the loop, >= 2 (default: 3)"
    )
    parser.add_argument(
        "--size", type=parse_size, default=(320, 240), help="image WIDTHxHEIGHT (default: 320x240)"
    )
    parser.add_argument(
        "--compressed",
        action="store_true",
        help=f"write JPEG CompressedImage on {COMPRESSED_TOPIC}",
    )
    noise = OdometryNoise()
    parser.add_argument(
        "--odom-scale-error",
        type=float,
        default=noise.scale_error,
        metavar="F",
        help=f"{ODOM_TOPIC} reads distances (1 + F) times too long (default: %(default)s)",
    )
    parser.add_argument(
        "--odom-yaw-bias",
        type=float,
        default=noise.yaw_rate_bias_deg_s,
        metavar="DEG_S",
        help=f"{ODOM_TOPIC}'s yaw-rate bias in deg/s (default: %(default)s)",
    )
    parser.add_argument(
        "--mono",
        action="store_true",
        help=f"write {IMAGE_TOPIC} as mono8 (a grey camera; grey JPEGs with --compressed)",
    )
    parser.add_argument(
        "--no-depth", action="store_true", help=f"leave out {DEPTH_TOPIC} (smaller, faster bag)"
    )
    parser.add_argument(
        "--fleet",
        action="store_true",
        help="write the demo fleet instead: OUT is a folder that gets one bag per robot-session "
        "(robots a, b, c on one clock from three points of the loop, a again a day later at "
        "dusk; odometry from each robot's own origin) and fleet.json; --frames is per drive "
        "(default 300 with --fleet)",
    )
    parser.add_argument(
        "--rig",
        action="store_true",
        help=f"a robot with a rear camera too ({REAR_IMAGE_TOPIC}, its camera_info and depth, "
        "both cameras' poses on /tf_static; issue 49), and lap 1 driven the other way round: "
        "the world of make demo-rig",
    )
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")
    parser.add_argument("--dataset", type=Path, help="also write a place dataset to this folder")
    parser.add_argument(
        "--places", type=int, default=100, help="places in the dataset (default: 100)"
    )
    parser.add_argument("--views", type=int, default=6, help="views per place, >= 4 (default: 6)")
    parser.add_argument("--progress", action="store_true", help="show progress bars")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Exit codes: `pair_vpr_ros.cli` (0 done, 1 error, 2 usage, 130 Ctrl-C)."""
    return run_cli(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> None:
    if args.out is None and args.dataset is None:
        raise UsageError("give an output bag path (OUT) and/or --dataset DIR")
    if args.fleet and args.rig:
        raise UsageError("--rig and --fleet do not go together: fleet robots have one camera")
    if args.fleet:
        if args.out is None:
            raise UsageError("--fleet needs an output folder (OUT)")
        _fleet(args)
    elif args.out is not None:
        start = time.perf_counter()
        world = generate_world(
            args.seed,
            frames=args.frames,
            laps=args.laps,
            width=args.size[0],
            height=args.size[1],
            reverse_laps=RIG_REVERSE_LAPS if args.rig else (),
        )
        path = write_world_bag(
            world,
            args.out,
            compressed=args.compressed,
            force=args.force,
            progress=args.progress,
            depth=not args.no_depth,
            mono=args.mono,
            odometry=OdometryNoise(
                scale_error=args.odom_scale_error, yaw_rate_bias_deg_s=args.odom_yaw_bias
            ),
            rear=args.rig,
        )
        print(
            f"wrote {path}: {world.num_frames} frames {args.size[0]}x{args.size[1]} "
            f"({'jpeg' if args.compressed else 'mono8' if args.mono else 'rgb8'}"
            f"{', front and rear cameras, lap 1 the other way round' if args.rig else ''}), "
            f"{world.config.laps} laps = "
            f"{world.loops} loops, {len(world.revisit_pairs())} revisit frames, "
            f"seed {args.seed}, {time.perf_counter() - start:.1f} s"
        )
    if args.dataset is not None:
        start = time.perf_counter()
        root = write_place_dataset(
            args.dataset,
            seed=args.seed,
            places=args.places,
            views_per_place=args.views,
            size=args.size,
            force=args.force,
            progress=args.progress,
        )
        print(
            f"wrote {root}: {args.places} places x {args.views} views {args.size[0]}x"
            f"{args.size[1]}, seed {args.seed}, {time.perf_counter() - start:.1f} s"
        )


def _fleet(args: argparse.Namespace) -> None:
    from pair_vpr_ros.demo.fleet import write_fleet_bags

    start = time.perf_counter()
    frames = 300 if args.frames == WorldConfig.frames else args.frames
    manifest = write_fleet_bags(
        args.out, seed=args.seed, frames=frames, size=args.size, force=args.force,
        progress=args.progress, odometry=OdometryNoise(
            scale_error=args.odom_scale_error, yaw_rate_bias_deg_s=args.odom_yaw_bias),
    )  # fmt: skip
    print(f"wrote {manifest} and its bags: {frames} frames per drive, seed {args.seed}, "
          f"{time.perf_counter() - start:.1f} s")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
