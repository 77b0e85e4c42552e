"""Bag replay throughput: frames/s of `replay_bag` (bag reading, decoding, encoder, map, rerank).

Replays a bag (by default a freshly written demo bag, `pair_vpr_ros.demo.write_demo_bag`) with a
checkpoint or a random-init preset (`tiny`, `small`, `S`, `B`, ...: a network's speed does
not depend on its weights) and prints one line per run; the first run includes warm-up. Random
weights make all frames look alike, so by default every frame is made a keyframe (queried and
re-ranked once 30 s of map exist): the worst case for the pipeline.

    python benchmarks/bench_replay.py --preset small --frames 240 --batch-size 8 --repeat 2
    python benchmarks/bench_replay.py --bag my.mcap --topic /cam --weights pairvpr-vitB.pth
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import torch

from pair_vpr_ros.errors import PairVPRError
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.model import ModelConfig, build_pairvpr, load_pairvpr
from pair_vpr_ros.model.threads import apply_threads, resolve_threads
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bag", help="bag to replay (default: write a demo bag to a temp folder)")
    p.add_argument("--topic", help="image topic, when the bag has several")
    p.add_argument("--weights", help="checkpoint; default: random-init --preset")
    p.add_argument("--preset", default="tiny", help="model preset without --weights (%(default)s)")
    p.add_argument("--frames", type=int, default=480, help="demo bag frames (%(default)s)")
    p.add_argument("--size", default="320x240", help="demo image size WxH (%(default)s)")
    p.add_argument("--compressed", action="store_true", help="demo bag with JPEG images")
    p.add_argument("--device", default="cpu", help="torch device (%(default)s)")
    p.add_argument("--batch-size", type=int, default=8, help="encoder batch (%(default)s)")
    p.add_argument("--top-k", type=int, default=10, help="candidates re-ranked (%(default)s)")
    p.add_argument(
        "--keyframe-max-similarity", type=float, default=1.0,
        help="detector keyframe_max_similarity (%(default)s: every frame is a keyframe)",
    )  # fmt: skip
    p.add_argument(
        "--threads", type=int, default=0,
        help="CPU threads of every pool (model/threads.py; 0: auto, as the replay's --threads)",
    )  # fmt: skip
    p.add_argument("--repeat", type=int, default=1, help="runs (the first includes warm-up)")
    return p.parse_args(argv)


def make_model(args: argparse.Namespace):
    if args.weights:
        return load_pairvpr(args.weights, device=args.device)
    torch.manual_seed(0)
    return build_pairvpr(ModelConfig.preset(args.preset)).to(args.device).eval()


def demo_bag(args: argparse.Namespace, folder: Path) -> Path:
    from pair_vpr_ros.demo.bag import write_demo_bag

    width, height = (int(v) for v in args.size.lower().split("x"))
    bag = folder / "demo.mcap"
    return write_demo_bag(
        bag, frames=args.frames, compressed=args.compressed, size=(width, height), depth=False
    )


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-replay-") as tmp:
        try:
            bag = Path(args.bag) if args.bag else demo_bag(args, Path(tmp))
            model = make_model(args)
            apply_threads(resolve_threads(args.threads, model.config))
            config = DetectorConfig(
                top_k=args.top_k, keyframe_max_similarity=args.keyframe_max_similarity
            )
            for run in range(args.repeat):
                s = replay_bag(
                    bag, Path(tmp) / f"out{run}", ReplayOptions(
                        topic=args.topic, batch_size=args.batch_size, save_map=False,
                        progress=False,
                    ), model=model, config=config,
                )  # fmt: skip
                name = args.weights or f"random {args.preset}"
                print(
                    f"replay {bag.name}: {name} ({model.config.image_size}px) on {args.device}, "
                    f"batch {args.batch_size}, top-k {args.top_k}, {torch.get_num_threads()} "
                    f"threads, cpus {os.cpu_count()}, run {run + 1}: {s.line()}"
                )
        except PairVPRError as err:
            print(f"error: {err}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
