"""Which transform before 4-bit quantising would let the re-ranking keep float16's winners
(issue 34's target: top-1 agreement >= 99 %, AP within 0.005), measured on the demo model.

Not the map's codecs (those are in bench_dense_codec.py): each route here quantises in float64
and decodes at once, at the byte size of one q4 entry (N D / 2 + 2 D bytes) minus the route's own
side information (scales, offsets and bits of each quantised row or column, counted as below), so
the routes compare at equal bytes. A stored basis (PCA) is not counted: it is once per map.
Routes:
- q4 / q4a: the map's codecs (dense_codec.py), for reference.
- hadamard-token: a fixed randomized Hadamard rotation over channels (seed 0, D a power of two),
  then 4 bits with one float16 scale per token (max |y| / 7).
- hadamard-channel: the same rotation, then q4's per-channel scales.
- channel-bits: no transform; integer bits per channel (0-8, greedy on range^2), each channel on
  its own range (float16 low end and step, 4-bit width: 4.5 D bytes of side information).
- token-dct: an orthonormal 2-D DCT over the token grid (N a square), bits per DCT row as above.
- pca-K: a PCA basis over channels fitted on the tokens of the first K frames (pca-all: all),
  bits per component as above.
- pca-16-stored: what a map could store (a basis fitted once, on its first 16 keyframes): those
  16 coded as channel-bits, the basis fitted on their decoded tokens, every later frame in it.

Each frame is a query against its k nearest others by global descriptor, re-ranked as
config/demo.yaml does (pair score + global_weight x descriptor similarity) with float16 tokens
and with the tokens through the route: both query and candidates (as bench_dense_codec.py), and
the query's own float16 tokens against candidates through the route (as the pipeline re-ranks: the
query's tokens come from the network, the candidates' from the map). Printed per route: top-1
agreement with float16 both ways, signal-to-noise of the decoded tokens (dB), mean and largest
change of a re-rank score (both coded), re-ranked top-1 AP (both coded).

    python benchmarks/bench_dense_routes.py --queries 300 --k 5 --global-weight 100
"""

from __future__ import annotations

import heapq
import sys

import numpy as np
import torch
from bench_dense_codec import setup, top1_ap
from bench_model import rerank_scores
from scipy.fft import dct

from pair_vpr_ros.loops.records import rerank_score
from pair_vpr_ros.place_map.dense_codec import decode, encode


def allocate(energy: np.ndarray, total: int) -> np.ndarray:
    """Integer bits 0..8 per row of `energy` [R] (greedy: each bit where it cuts the most
    squared error, energy x 4^-bits), `total` bits in all."""
    bits = np.zeros(len(energy), int)
    heap = [(-float(e), i) for i, e in enumerate(energy)]
    heapq.heapify(heap)
    for _ in range(min(total, 8 * len(energy))):
        e, i = heapq.heappop(heap)
        bits[i] += 1
        if bits[i] < 8:
            heapq.heappush(heap, (e / 4, i))
    return bits


def quantise_columns(y: np.ndarray, budget_bytes: int) -> np.ndarray:
    """y [M, R]: each column on its own range with its allocated bits (side information 4.5
    bytes a column, float16 ends) -> decoded [M, R]."""
    m, r = y.shape
    total = (budget_bytes - (9 * r + 1) // 2 - 8) * 8 // m  # 8: padding of the bit groups
    lo = y.min(0).astype(np.float16).astype(np.float64)
    span = y.max(0) - lo
    bits = allocate(span**2, total)
    levels = (2.0**bits - 1).astype(np.float64)
    step = np.where(levels > 0, span / np.maximum(levels, 1), 0.0)
    step = step.astype(np.float16).astype(np.float64)
    q = np.clip(np.rint((y - lo) / np.where(step > 0, step, 1)), 0, levels)
    return np.where(levels > 0, lo + q * step, lo + span / 2)


def symmetric4(y: np.ndarray, axis: int) -> np.ndarray:
    """4 bits, levels -7..7, one float16 scale (max |y| / 7) along `axis`'s other axis."""
    scale = (np.abs(y).max(axis=axis, keepdims=True) / 7).astype(np.float16).astype(np.float64)
    safe = np.where(scale > 0, scale, 1)
    return np.clip(np.rint(y / safe), -7, 7) * scale


def routes(tokens: np.ndarray, n: int, d: int) -> dict:
    """Route name -> function tokens [N, D] float16 -> decoded [N, D] float16."""
    budget = (n * d + 1) // 2 + 2 * d
    rng = np.random.default_rng(0)
    had = np.array([[1.0]])
    while had.shape[0] < d:
        had = np.block([[had, had], [had, -had]])
    rot = had / np.sqrt(d) * rng.choice([-1.0, 1.0], d)[None, :]  # y = x @ rot.T
    g = int(round(np.sqrt(n)))
    grid = np.kron(dct(np.eye(g), norm="ortho", axis=0), dct(np.eye(g), norm="ortho", axis=0))
    out = {
        "q4": lambda t: decode(encode(t, "q4"), t.shape, "q4"),
        "q4a": lambda t: decode(encode(t, "q4a"), t.shape, "q4a"),
        "channel-bits": lambda t: quantise_columns(t.astype(np.float64), budget),
    }
    if had.shape[0] == d:
        out["hadamard-token"] = lambda t: symmetric4(t.astype(np.float64) @ rot.T, 1) @ rot
        out["hadamard-channel"] = lambda t: symmetric4(t.astype(np.float64) @ rot.T, 0) @ rot
    if g * g == n:
        out["token-dct"] = lambda t: grid.T @ quantise_columns(grid @ t.astype(np.float64), budget)
    flat = tokens.astype(np.float64)
    for fitted in (1, 4, 16, len(tokens)):
        sample = flat[:fitted].reshape(-1, d)
        mean = sample.mean(0)
        basis = np.linalg.eigh(np.cov((sample - mean).T))[1][:, ::-1].astype(np.float16)
        basis = basis.astype(np.float64)  # stored as float16, once per map

        def pca(t, mean=mean, basis=basis):
            y = quantise_columns((t.astype(np.float64) - mean) @ basis, budget)
            return y @ basis.T + mean

        out[f"pca-{fitted if fitted < len(tokens) else 'all'}"] = pca
    first = np.stack([out["channel-bits"](t) for t in tokens[:16]]).reshape(-1, d)
    mean = first.mean(0)
    basis = np.linalg.eigh(np.cov((first - mean).T))[1][:, ::-1].astype(np.float16)
    out["pca-16-stored"] = _Stored(out["channel-bits"], out["pca-16"], mean, basis)
    return out


class _Stored:
    """Frames 0..15 through `plain`, later ones in the basis fitted on those decoded (called
    once per frame, in order)."""

    def __init__(self, plain, like, mean: np.ndarray, basis: np.ndarray) -> None:
        self.plain, self.count = plain, 0
        self.coded = lambda t: like(t, mean=mean, basis=basis.astype(np.float64))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        self.count += 1
        return self.plain(t) if self.count <= 16 else self.coded(t)


@torch.inference_mode()
def main(argv: list[str] | None = None) -> int:
    args, model, images, places = setup(argv, __doc__)
    dense, desc = model.encode(images)
    tokens = dense.half().numpy()  # [Q, N, D], what a float16 map stores
    sims = (desc @ desc.T).fill_diagonal_(-2.0)
    nearest = sims.topk(args.k, dim=1).indices
    floats = torch.from_numpy(tokens).float()
    base = rerank_scores(model, floats, desc, nearest, args.global_weight)
    top2 = base.topk(2, dim=1).values
    margin = top2[:, 0] - top2[:, 1]
    print(f"float16: top-1 / top-2 margin median {float(margin.median()):.3f}, below 0.2 for "
          f"{int((margin < 0.2).sum())} of {len(margin)} queries")  # fmt: skip
    print("| route | top-1 agreement, both coded | query float16 | SNR dB | score change mean / "
          "max | re-ranked AP |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    power = float((tokens.astype(np.float64) ** 2).mean())
    for name, route in routes(tokens, *tokens.shape[1:]).items():
        back = np.stack([np.asarray(route(t), np.float64) for t in tokens]).astype(np.float16)
        noise = float(((back.astype(np.float64) - tokens) ** 2).mean())
        got = rerank_scores(model, torch.from_numpy(back).float(), desc, nearest,
                            args.global_weight)  # fmt: skip
        same = int((got.argmax(1) == base.argmax(1)).sum())
        pair = torch.stack([model.pair_scores(floats[i],
                                              torch.from_numpy(back[o]).float())
                            for i, o in enumerate(nearest)])  # fmt: skip
        similar = torch.stack([desc[o] @ desc[i] for i, o in enumerate(nearest)])
        fresh = rerank_score(pair, similar, args.global_weight)
        kept = int((fresh.argmax(1) == base.argmax(1)).sum())
        change = (got - base).abs()
        ap = top1_ap(got, nearest, places)[0]
        print(f"| {name} | {same / len(tokens):.4f} ({len(tokens) - same} differ) | "
              f"{kept / len(tokens):.4f} ({len(tokens) - kept} differ) | "
              f"{10 * np.log10(power / noise):.1f} | {float(change.mean()):.3f} / "
              f"{float(change.max()):.3f} | {ap:.4f} |", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
