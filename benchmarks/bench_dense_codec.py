"""What the map's 4-bit dense tokens (dense_codec q4a, q4, p4) cost the re-ranking (issue 34).

Demo-world frames (benchmarks/bench_model.py's `agreement_images`: spread over the laps of the
seed-1234 world, revisits included) are encoded by the shipped demo model; each frame is a query
whose k nearest others by global descriptor are its candidates, re-ranked as config/demo.yaml
does (pair score + global_weight x descriptor similarity) once with the float16 tokens the map
stored before and once with the same tokens through each 4-bit codec (what a map gives back;
p4: the frames added in order to a dense store, its basis fitted on the first BASIS_FROM for the
model's decoder_embed, and "p4-channels" on the tokens' own channels).

Reported: top-1 agreement (the same candidate wins), the same place (top-1 within the replay's
ground-truth radius of float16's), and the AP / recall at precision 0.9 of the re-ranked top-1 as
a loop detection (correct: the winner lies within that radius of the query), per codec; each
query whose winner changes (float16's margin over the codec's winner, the codec's margin the
other way, how far apart the two winners are); and each codec's encode and decode time for one
ViT-B/322 keyframe [529, 768] of random tokens (median of 20).
Transforms before quantising that might keep more winners: bench_dense_routes.py.
Targets (issue 34): agreement >= 99 %, AP within 0.005 of float16's.

    python benchmarks/bench_dense_codec.py --queries 300 --k 5 --global-weight 100
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from bench_model import SAME_PLACE_M, agreement, agreement_images, default_demo_weights

from pair_vpr_ros.learn.heldout import average_precision
from pair_vpr_ros.model import load_pairvpr
from pair_vpr_ros.place_map.dense_codec import BASIS_FROM, Basis, decode, encode, entry_bytes
from pair_vpr_ros.place_map.dense_store import DenseStore


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


class MapStored(StoredAs):
    """Dense tokens as a p4 map gives them back: the frames added in order to a dense store
    (the first BASIS_FROM as q4, then the basis fitted on them; `weight`: the decoder's W)."""

    def __init__(self, model, weight: np.ndarray | None) -> None:
        super().__init__(model, "p4")
        self.weight = weight

    def encode(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        dense, desc = self.model.encode(images)
        shape = tuple(dense.shape[1:])
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "d.p4"  # owned: a new map's working file, as the pipeline's
            store = DenseStore(path, shape, codec="p4", weight=self.weight, owned=True)
            for t in dense.float():
                store.append(np.ascontiguousarray(t.half().numpy()))
            stored = store.read(np.arange(store.count))
            store.close()
        return torch.from_numpy(stored).to(dense.dtype), desc


def loop_ap(model, images, places, k: int, weight: float) -> tuple[float, float]:
    """AP and recall@P90 of each query's re-ranked top-1 as a loop (within SAME_PLACE_M)."""
    from bench_model import rerank_scores

    with torch.inference_mode():
        dense, desc = model.encode(images)
        sims = (desc @ desc.T).fill_diagonal_(-2.0)
        nearest = sims.topk(k, dim=1).indices
        scores = rerank_scores(model, dense, desc, nearest, weight)
    return top1_ap(scores, nearest, places)


def top1_ap(scores: torch.Tensor, nearest: torch.Tensor, places) -> tuple[float, float]:
    """AP and recall@P90 of each query's top-1 by scores [Q, k] of its candidates nearest
    [Q, k], as a loop (correct: within SAME_PLACE_M of the query, places [Q, 2] m)."""
    top, pick = scores.max(1)
    chosen = places[nearest.gather(1, pick[:, None])[:, 0].numpy()]
    correct = np.linalg.norm(chosen - places, axis=1) <= SAME_PLACE_M
    return average_precision(top.numpy(), correct)


def setup(argv: list[str] | None, doc: str):
    """The demo model and its frames: -> (args, model, images [Q, 3, S, S], places [Q, 2])."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--queries", type=int, default=300, help="demo-world frames (default 300)")
    p.add_argument("--k", type=int, default=5, help="candidates re-ranked (config/demo.yaml: 5)")
    p.add_argument("--global-weight", type=float, default=100.0, help="(config/demo.yaml: 100)")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    model = load_pairvpr(default_demo_weights())
    return (args, model, *agreement_images(model.config.image_size, args.queries))


def main(argv: list[str] | None = None) -> int:
    args, model, images, places = setup(argv, __doc__)
    paths = {"fp32": StoredAs(model, "f16")} | {c: StoredAs(model, c) for c in ("q4", "q4a")}
    weight = model.decoder_embed.weight.detach().float().numpy()
    paths |= {"p4": MapStored(model, weight), "p4-channels": MapStored(model, None)}
    found = agreement(paths, images, args.k, places, args.global_weight)
    for codec in [name for name in paths if name != "fp32"]:
        f = found[codec]
        print(f"{codec} vs f16 tokens, {args.queries} queries, top {args.k}, global weight "
              f"{args.global_weight:g}: top-1 agreement {f['top1']:.4f}, same place "
              f"{f['same_place']:.4f}, largest score lost {f['regret_max']:.3f}")  # fmt: skip
        for i, lost, gap, apart in f["flips"]:  # which queries change winner, and by how much
            print(f"  query {i}: float16's margin over the {codec} winner {lost:.3f}, "
                  f"{codec}'s {gap:.3f} the other way, winners {apart:.2f} m apart")  # fmt: skip
    for name, m in [("f16", paths["fp32"])] + [(c, paths[c]) for c in paths if c != "fp32"]:
        ap, r90 = loop_ap(m, images, places, args.k, args.global_weight)
        print(f"{name}: re-ranked top-1 AP {ap:.4f}, recall at precision 0.9 {r90:.4f}")
    print_speed()
    return 0


def print_speed(shape: tuple[int, int] = (529, 768), repeats: int = 20) -> None:
    """Median encode and decode time of one ViT-B/322 keyframe's tokens per codec."""
    rng = np.random.default_rng(0)
    tokens = rng.standard_normal(shape).astype(np.float16)
    # p4's basis fitted on random correlated tokens (every component gets bits: the slowest)
    mix = rng.standard_normal((shape[1], shape[1])) / np.sqrt(shape[1])
    fit = rng.standard_normal((BASIS_FROM * shape[0], shape[1])) @ mix
    basis = Basis.fit(fit, shape[0], entry_bytes(shape, "p4"), BASIS_FROM)
    for codec in ("f16", "q4", "q4a", "p4"):
        enc, dec = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            if codec == "p4":
                data = basis.encode(tokens, entry_bytes(shape, "p4"))
            else:
                data = encode(tokens, codec)
            t1 = time.perf_counter()
            basis.decode(data, shape[0]) if codec == "p4" else decode(data, shape, codec)
            enc.append(t1 - t0)
            dec.append(time.perf_counter() - t1)
        print(f"{codec} [{shape[0]}, {shape[1]}]: {len(data):,} B, encode "
              f"{1e3 * np.median(enc):.2f} ms, decode {1e3 * np.median(dec):.2f} ms")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
