"""Encoding a rig keyframe (issue 49): the N cameras' frames of one instant as one batch, as the
pipeline encodes them, against N single-frame encodes (what N single-camera nodes would do).

    python benchmarks/bench_rig_encode.py                   # ViT-B/322 random weights, 2 and 4
    python benchmarks/bench_rig_encode.py --model demo --cameras 2

Speed does not depend on the weights, so random ViT-B weights measure the released model's.
Each rig keyframe is encoded through `LoopClosurePipeline.encode` (preprocessing included) from
demo-world frames (320 x 240); the two ways run in turn `--repeat` times after a warm-up and
the medians are printed, per rig keyframe, with their ratio.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import torch

from pair_vpr_ros.demo import generate_world, render_frame
from pair_vpr_ros.demo.rig import render_rear
from pair_vpr_ros.geometry.camera_notes import DEMO_WEIGHTS
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.model import ModelConfig, build_pairvpr, load_pairvpr


def medians(fns: dict, repeat: int) -> dict[str, float]:
    """Median ms of each function, run in turn `repeat` times after one warm-up each."""
    times: dict[str, list[float]] = {name: [] for name in fns}
    for fn in fns.values():
        fn()
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - t0) * 1e3)
    return {name: float(np.median(t)) for name, t in times.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--model",
        choices=("vitb", "demo"),
        default="vitb",
        help="vitb: ViT-B/322, random weights; demo: the shipped demo model",
    )
    p.add_argument("--cameras", type=int, nargs="+", default=[2, 4], help="rig sizes N")
    p.add_argument("--repeat", type=int, default=5, help="timed runs of each way")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    args = p.parse_args()  # fmt: skip
    if args.threads:
        torch.set_num_threads(args.threads)
    model = build_pairvpr(ModelConfig(), seed=0) if args.model == "vitb" else \
        load_pairvpr(DEMO_WEIGHTS)  # fmt: skip
    pipe = LoopClosurePipeline(model)
    world = generate_world(7, frames=600, reverse_laps=(1,))
    views = [render_frame(world, 10), render_rear(world, 10), render_frame(world, 300),
             render_rear(world, 300)]  # fmt: skip
    print(f"{platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, model {args.model}")  # fmt: skip
    for n in args.cameras:
        frames = [views[i % len(views)] for i in range(n)]
        got = medians({
            "rig batch": lambda f=frames: pipe.encode(f),
            "single frames": lambda f=frames: [pipe.encode([x]) for x in f],
        }, args.repeat)  # fmt: skip
        ratio = got["rig batch"] / got["single frames"]
        print(f"N={n}: one batch {got['rig batch']:.1f} ms, {n} single frames "
              f"{got['single frames']:.1f} ms per rig keyframe: {ratio:.2f}x")  # fmt: skip
    pipe.close()


if __name__ == "__main__":
    main()
