"""What the map's 4-bit dense tokens (dense_codec "q4a", "q4") cost the re-ranking (issue 34).

Demo-world frames (benchmarks/bench_model.py's `agreement_images`: spread over the laps of the
seed-1234 world, revisits included) are encoded by the shipped demo model; each frame is a query
whose k nearest others by global descriptor are its candidates, re-ranked as config/demo.yaml
does (pair score + global_weight x descriptor similarity) once with the float16 tokens the map
stored before and once with the same tokens through each 4-bit codec (what a map gives back).

Reported: top-1 agreement (the same candidate wins), the same place (top-1 within the replay's
ground-truth radius of float16's), and the AP / recall at precision 0.9 of the re-ranked top-1 as
a loop detection (correct: the winner lies within that radius of the query), per codec.
Targets (issue 34): agreement >= 99 %, AP within 0.005 of float16's.

    python benchmarks/bench_dense_codec.py --queries 300 --k 5 --global-weight 100
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
import torch
from bench_model import SAME_PLACE_M, agreement, agreement_images, default_demo_weights

from pair_vpr_ros.learn.heldout import average_precision
from pair_vpr_ros.model import load_pairvpr
from pair_vpr_ros.place_map.dense_codec import decode, encode


class StoredAs:
    """A model whose dense tokens come back as a map of `codec` stores them ([N, T, D])."""

    def __init__(self, model, codec: str) -> None:
        self.model, self.codec = model, codec

    def encode(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        dense, desc = self.model.encode(images)
        stored = [
            decode(encode(t.half().numpy(), self.codec), tuple(t.shape), self.codec)
            for t in dense.float()
        ]
        return torch.from_numpy(np.stack(stored)).to(dense.dtype), desc

    def pair_scores(self, *args):
        return self.model.pair_scores(*args)


def loop_ap(model, images, places, k: int, weight: float) -> tuple[float, float]:
    """AP and recall@P90 of each query's re-ranked top-1 as a loop (within SAME_PLACE_M)."""
    from bench_model import rerank_scores

    with torch.inference_mode():
        dense, desc = model.encode(images)
        sims = (desc @ desc.T).fill_diagonal_(-2.0)
        nearest = sims.topk(k, dim=1).indices
        scores = rerank_scores(model, dense, desc, nearest, weight)
    top, pick = scores.max(1)
    chosen = places[nearest.gather(1, pick[:, None])[:, 0].numpy()]
    correct = np.linalg.norm(chosen - places, axis=1) <= SAME_PLACE_M
    return average_precision(top.numpy(), correct)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--queries", type=int, default=300, help="demo-world frames (default 300)")
    p.add_argument("--k", type=int, default=5, help="candidates re-ranked (config/demo.yaml: 5)")
    p.add_argument("--global-weight", type=float, default=100.0, help="(config/demo.yaml: 100)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    model = load_pairvpr(default_demo_weights())
    images, places = agreement_images(model.config.image_size, args.queries)
    paths = {"fp32": StoredAs(model, "f16")} | {c: StoredAs(model, c) for c in ("q4", "q4a")}
    found = agreement(paths, images, args.k, places, args.global_weight)
    for codec in ("q4", "q4a"):
        f = found[codec]
        print(f"{codec} vs f16 tokens, {args.queries} queries, top {args.k}, global weight "
              f"{args.global_weight:g}: top-1 agreement {f['top1']:.4f}, same place "
              f"{f['same_place']:.4f}, largest score lost {f['regret_max']:.3f}")  # fmt: skip
    for name, m in (("f16", paths["fp32"]), ("q4", paths["q4"]), ("q4a", paths["q4a"])):
        ap, r90 = loop_ap(m, images, places, args.k, args.global_weight)
        print(f"{name}: re-ranked top-1 AP {ap:.4f}, recall at precision 0.9 {r90:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
