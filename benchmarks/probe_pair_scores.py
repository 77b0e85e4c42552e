"""Why an exact duplicate frame gets a low pair score from the demo model (issue 13, item 13).

Part 1 checks the pair path itself: for the same query, the score of an identical candidate
through float16 (as stored in the map) and float32 tokens, the batched fast path with chunks of
1, 2 and all candidates, and the one-pair-at-a-time reference path; and the score of a
near-identical candidate (the image plus +-2 grey levels of noise). Part 2 scores every pair of
a sample of demo-world frames and groups the scores by what the two frames share: identical,
same lap (same lighting and parked cars), different lap (revisits and non-revisits).

    python benchmarks/probe_pair_scores.py [--weights pair_vpr_ros/demo/assets/demo-small.pth]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from pair_vpr_ros.demo import generate_world, render_frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.model import load_pairvpr, preprocess_batch

DEMO = Path(__file__).parents[1] / "pair_vpr_ros" / "demo" / "assets" / "demo-small.pth"


def part_one(model, pipe, world, frames: list[int]) -> None:
    print("| frame | identical fp16 | identical fp32 | chunk 1 | chunk 2 | reference | "
          "+-2 noise | global sim with noise |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(0)
    for i in frames:
        rgb = render_frame(world, i)
        noisy = np.clip(rgb.astype(int) + rng.integers(-2, 3, rgb.shape), 0, 255).astype(np.uint8)
        dense16, desc = pipe.encode([rgb, noisy])
        q16, n16 = (torch.from_numpy(d).float() for d in dense16)
        with torch.inference_mode():
            q32 = model.encode(preprocess_batch([rgb], model.config.image_size))[0][0].float()
            same = torch.stack([q16, q16, q16])
            row = [
                model.pair_scores(q16, q16[None]).item(),
                model.pair_scores(q32, q32[None]).item(),
                model.pair_scores(q16, same, chunk=1)[1].item(),
                model.pair_scores(q16, same, chunk=2)[2].item(),
                model.pair_scores_reference(q16, q16[None]).item(),
                model.pair_scores(q16, n16[None]).item(),
            ]
        cells = " | ".join(f"{v:.4f}" for v in row)
        print(f"| {i} | {cells} | {float(desc[0] @ desc[1]):.5f} |")


def part_two(model, pipe, world, step: int) -> None:
    ids = list(range(0, len(world.stamps), step))
    dense, desc = pipe.encode([render_frame(world, i) for i in ids])
    tokens = torch.from_numpy(dense).float()
    with torch.inference_mode():
        scores = torch.stack([model.pair_scores(tokens[a], tokens) for a in range(len(ids))])
    scores = scores.numpy()
    lap = np.asarray(world.lap)[ids]
    groups = {
        "identical": np.eye(len(ids), dtype=bool),
        "same lap, other frame": (lap[:, None] == lap[None, :]) & ~np.eye(len(ids), dtype=bool),
        "different lap": lap[:, None] != lap[None, :],
    }
    print(f"\n{len(ids)} frames (every {step}th), {len(ids) ** 2} ordered pairs")
    print("| pairs | n | pair score mean | min | max | share > 0 | global sim mean |")
    print("|---|---|---|---|---|---|---|")
    sims = desc @ desc.T
    for name, mask in groups.items():
        s = scores[mask]
        print(
            f"| {name} | {mask.sum()} | {s.mean():.3f} | {s.min():.3f} | {s.max():.3f} | "
            f"{np.mean(s > 0):.2f} | {sims[mask].mean():.3f} |"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", type=Path, default=DEMO, help="checkpoint (default: demo model)")
    p.add_argument("--seed", type=int, default=7, help="demo world seed (default: %(default)s)")
    p.add_argument("--step", type=int, default=12, help="frame step of part 2 (default: 12)")
    args = p.parse_args()
    model = load_pairvpr(args.weights)
    pipe = LoopClosurePipeline(model)
    world = generate_world(args.seed)
    part_one(model, pipe, world, [0, 80, 160, 240, 400])
    part_two(model, pipe, world, args.step)
    pipe.close()


if __name__ == "__main__":
    main()
