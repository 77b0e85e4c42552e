"""Network speed on the current device: encode, re-rank (fast vs reference, fp32 vs int8), memory,
and how closely int8 agrees with fp32.

    python benchmarks/bench_model.py                      # ViT-B/322, random weights, CPU
    python benchmarks/bench_model.py --weights pairvpr-vitB.pth --device cuda --precision bf16
    python benchmarks/bench_model.py --k 10 --quick        # a minute on a laptop

Speed does not depend on the weights, so random ViT-B weights measure the released model's
speed. Agreement does: with random weights all pair scores are near-ties, so it is measured with
`--agreement-weights` (default: the shipped demo model on demo-world images) and reported with
which model it used.
"""

from __future__ import annotations

import argparse
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

from pair_vpr_ros.model import ModelConfig, build_pairvpr, load_pairvpr, quantize_int8
from pair_vpr_ros.model.config import PATCH


def interleaved(
    fns: dict[str, object], repeat: int, per: int, warmup: bool = True
) -> dict[str, float]:
    """Median ms per item of each function, run in turn `repeat` times (after one warm-up each):
    on a shared machine, timings taken minutes apart are not comparable."""
    times: dict[str, list[float]] = {name: [] for name in fns}
    for fn in fns.values() if warmup else ():
        fn()
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            times[name].append((time.perf_counter() - t0) * 1e3 / per)
    return {name: float(np.median(t)) for name, t in times.items()}


def encode_fns(models: dict, size: int, device: str, batch: int) -> dict:
    x = torch.randn(batch, 3, size, size, device=device)
    fns = {name: (lambda m=m: m.encode(x)) for name, m in models.items() if name != "reference"}
    fns["reference"] = lambda: models["reference"].encode(x, fast=False)
    return fns


def rerank_fns(models: dict, size: int, device: str, k: int, with_reference: bool) -> dict:
    n, d = (size // PATCH) ** 2, models["fp32"].config.embed_dim
    q, c = torch.randn(n, d, device=device), torch.randn(k, n, d, device=device)
    fns = {name: (lambda m=m: m.pair_scores(q, c)) for name, m in models.items()
           if name != "reference"}  # fmt: skip
    if with_reference:
        fns["reference"] = lambda: models["reference"].pair_scores_reference(q, c)
    return fns


def agreement(model, images: torch.Tensor, k: int) -> tuple[float, float, str]:
    """(top-1 agreement after re-ranking, mean descriptor cosine) of int8 vs fp32."""
    qmodel = quantize_int8(model)
    with torch.inference_mode():
        dense, desc = model.encode(images)
        qdense, qdesc = qmodel.encode(images)
        same = []
        for i in range(len(images)):
            others = [j for j in range(len(images)) if j != i][:k]
            s = model.pair_scores(dense[i], dense[others])
            qs = qmodel.pair_scores(qdense[i], qdense[others])
            same.append(int(s.argmax()) == int(qs.argmax()))
    cos = float((desc * qdesc).sum(-1).mean())
    return float(np.mean(same)), cos, f"{len(images)} queries x {k} candidates"


def agreement_images(model, count: int) -> torch.Tensor:
    from pair_vpr_ros.model import preprocess_batch

    try:
        from pair_vpr_ros.demo.render import render_frame
        from pair_vpr_ros.demo.world import generate_world

        world = generate_world(seed=1234)
        step = max(1, len(world.poses) // count)
        rgb = [render_frame(world, i) for i in range(0, step * count, step)]
    except Exception:  # demo world unavailable: random images
        rgb = [
            np.random.default_rng(i).integers(0, 256, (240, 320, 3), np.uint8)
            for i in range(count)
        ]
    return preprocess_batch(rgb, model.config.image_size)


def default_demo_weights() -> Path | None:
    path = Path(__file__).resolve().parents[1] / "pair_vpr_ros" / "demo" / "assets"
    found = sorted(path.glob("*.pth"))
    return found[0] if found else None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--weights", help="checkpoint to time (default: random weights of --arch)")
    p.add_argument("--arch", default="B", help="model preset when no weights are given")
    p.add_argument("--image-size", type=int, default=322, help="input size in pixels")
    p.add_argument("--device", default="cpu", help="cpu or cuda[:N]")
    p.add_argument(
        "--k", default="10,100", help="candidate counts for re-ranking, comma-separated"
    )
    p.add_argument("--repeat", type=int, default=3, help="timed runs of each path (median)")
    p.add_argument("--quick", action="store_true", help="skip the reference path at the largest K")
    p.add_argument(
        "--agreement-weights",
        help="model for the int8 agreement check (default: the shipped demo model)",
    )
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    ks = [int(k) for k in args.k.split(",")]
    if args.weights:
        model = load_pairvpr(args.weights, device=args.device, image_size=args.image_size)
    else:
        cfg = ModelConfig.preset(args.arch, image_size=args.image_size)
        model = build_pairvpr(cfg, device=args.device, seed=0)
    size = model.config.image_size
    cpu = platform.processor() or platform.machine()
    print(
        f"# Pair-VPR {model.config.arch}/{size}px on {args.device} ({cpu}, "
        f"{torch.get_num_threads()} threads, torch {torch.__version__})"
    )
    models = {"fp32": model, "reference": model}
    if args.device == "cpu":
        models["int8"] = quantize_int8(model)
    rows = []
    with torch.inference_mode():
        for batch in (1, 8):
            t = interleaved(encode_fns(models, size, args.device, batch), args.repeat, batch)
            rows.append((f"encode, batch {batch} (ms/image)", t))
        for k in ks:
            skip_ref = args.quick and k == max(ks) and len(ks) > 1
            fns = rerank_fns(models, size, args.device, k, not skip_ref)
            # Kernels are warm by now; at large K one pass already averages K candidates.
            t = interleaved(fns, 1 if k >= 50 else args.repeat, k, warmup=False)
            rows.append((f"re-rank K={k} (ms/candidate)", t))
    print("| figure | fp32 fast | int8 fast | fp32 reference | fast/ref | int8/ref |")
    print("|---|---|---|---|---|---|")
    nan = float("nan")
    for name, t in rows:
        fast, q, ref = t["fp32"], t.get("int8", nan), t.get("reference", nan)
        print(f"| {name} | {fast:.1f} | {q:.1f} | {ref:.1f} | {fast / ref:.2f} | {q / ref:.2f} |")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak resident memory: {peak:.0f} MiB")
    if torch.cuda.is_available() and args.device.startswith("cuda"):
        print(f"peak GPU memory: {torch.cuda.max_memory_allocated() / 2**20:.0f} MiB")
    weights = args.agreement_weights or default_demo_weights()
    if weights is None:
        print("int8 agreement: skipped (no --agreement-weights and no shipped demo model)")
        return 0
    amodel = load_pairvpr(weights)
    top1, cos, what = agreement(amodel, agreement_images(amodel, 24), k=10)
    print(
        f"int8 vs fp32 ({Path(weights).name}, {what}): top-1 after re-ranking agrees "
        f"{top1:.1%}, mean descriptor cosine {cos:.5f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
