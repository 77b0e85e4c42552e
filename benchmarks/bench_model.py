"""Network speed on the current device: encode, re-rank (fast vs reference, fp32 vs int8, the
OpenVINO back end), memory, and how closely each path agrees with torch fp32.

    python benchmarks/bench_model.py                      # ViT-B/322, random weights, CPU
    python benchmarks/bench_model.py --k 10 --json out.json
    python benchmarks/bench_model.py --weights pairvpr-vitB.pth --device cuda
    python benchmarks/bench_model.py --agreement-only --calibration demo_seed9.mcap
    python benchmarks/bench_model.py --agreement-only --agreement-k 5 --agreement-global-weight 100

Paths: `fp32` (torch, fast path), `reference` (torch, plain path), `int8` (torch dynamic int8),
`openvino` (backend openvino, static int8 calibrated on synthetic scenes, as the node runs it) and
`openvino-fp32` (the exported graphs in f32: their agreement checks the export); with
`--calibration BAG_OR_FOLDER` also `openvino-calibrated` (static int8 calibrated on that
recording's images, as the node's `openvino_calibration` parameter does). Paths run in
turn, so their ratios share the machine's load.

Speed does not depend on the weights, so random ViT-B weights measure the released model's
speed. Agreement does: with random weights all pair scores are near-ties, so it is measured with
`--agreement-weights` (default: the shipped demo model on demo-world images) and reported with
which model it used; the descriptor cosine of the timed (ViT-B) paths is printed as well.
`--json PATH` writes {"paths": {NAME: {"encode_ms", "rerank_ms"}}, "agreement": {NAME: {"top1",
"cosine"}}}: encode per image at batch 1, re-rank per candidate (both directions) at the first K.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

from pair_vpr_ros.loops.records import rerank_score
from pair_vpr_ros.model import ModelConfig, build_pairvpr, load_pairvpr, quantize_int8
from pair_vpr_ros.model.config import PATCH
from pair_vpr_ros.model.threads import apply_threads, resolve_threads
from pair_vpr_ros.offline.bags.calibration import calibration_loader
from pair_vpr_ros.offline.replay.options import ReplayOptions

AGREEMENT_QUERIES = 100  # demo-world queries, each re-ranking its 10 nearest frames
SAME_PLACE_M = ReplayOptions().gt_radius  # what the replay report counts as one place


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


def variants(model, device: str, calibration=None) -> dict:
    """Every path this machine runs: name -> model (the reference is `model` run plainly).
    `calibration`: `calibration_loader`'s function, for the `openvino-calibrated` path."""
    out = {"fp32": model, "reference": model}
    if device != "cpu":
        return out
    out["int8"] = quantize_int8(model)
    if importlib.util.find_spec("openvino") and importlib.util.find_spec("nncf"):
        from pair_vpr_ros.model.openvino_backend import OpenVINOModel

        out["openvino"] = OpenVINOModel(model, "int8")
        if calibration is not None:
            images = calibration(model.config.image_size)
            out["openvino-calibrated"] = OpenVINOModel(model, "int8", calibration=images)
        out["openvino-bf16"] = OpenVINOModel(model, "bf16")
        out["openvino-fp32"] = OpenVINOModel(model, "fp32")
    else:
        print("openvino: skipped (pip install 'pair_vpr_ros[openvino]')")
    return out


def agreement(
    models: dict,
    images: torch.Tensor,
    k: int,
    places: np.ndarray | None = None,
    global_weight: float = 0.0,
) -> dict[str, dict[str, float]]:
    """Per path, against fp32 (each image a query, its k nearest others by fp32 descriptor the
    candidates of every path; re-ranked by the detector's score, pair score + `global_weight` x
    the path's own descriptor similarity): `top1`, the fraction of queries whose top-1 after
    re-ranking is the same candidate; `same_place`, whose top-1 is within `SAME_PLACE_M` of
    fp32's (with `places` [n, 2] m: the loop closure a back end would get is the same);
    `regret_max`, the largest fp32 score lost by taking the path's top-1 instead of fp32's;
    `cosine`, the mean descriptor cosine."""
    base = models["fp32"]
    with torch.inference_mode():
        dense, desc = base.encode(images)
        sims = (desc @ desc.T).fill_diagonal_(-2.0)
        nearest = sims.topk(k, dim=1).indices
        want = rerank_scores(base, dense, desc, nearest, global_weight)
        top2 = want.topk(2, dim=1).values
        margin = float((top2[:, 0] - top2[:, 1]).median())
        spread = float((want.max(1).values - want.min(1).values).median())
        print(
            f"fp32 scores: top-1 vs top-2 margin median {margin:.4f}, spread median {spread:.2f}"
        )
        out = {}
        for name, model in models.items():
            if name in ("fp32", "reference"):
                continue
            mdense, mdesc = model.encode(images)
            got = rerank_scores(model, mdense, mdesc, nearest, global_weight)
            best, pick = want.argmax(1), got.argmax(1)
            regret = want.max(1).values - want.gather(1, pick[:, None])[:, 0]
            # the queries whose top-1 differs: fp32's gap between its top-1 and the path's,
            # and the path's own gap the other way (how far it moved the two apart)
            flips = [
                [i, float(regret[i]), float(got[i, pick[i]] - got[i, best[i]])]
                for i in torch.nonzero(best != pick).flatten().tolist()
            ]
            out[name] = {
                "top1": float((best == pick).float().mean()),
                "cosine": float((desc.float() * mdesc.float()).sum(-1).mean()),
                "regret_max": float(regret.max()),
                "flips": flips,
            }
            if places is not None:
                chosen = [places[nearest[i, j]] for i, j in enumerate(pick.tolist())]
                truth = [places[nearest[i, j]] for i, j in enumerate(best.tolist())]
                dist = np.linalg.norm(np.array(chosen) - np.array(truth), axis=1)
                out[name]["same_place"] = float(np.mean(dist <= SAME_PLACE_M))
                for flip in flips:
                    flip.append(float(dist[flip[0]]))
    return out


def rerank_scores(
    model, dense: torch.Tensor, desc: torch.Tensor, nearest: torch.Tensor, global_weight: float
) -> torch.Tensor:
    """[Q, k] re-rank scores of each query's candidates `nearest` [Q, k], as the detector ranks
    them (`detector.rerank_score`: pair score + `global_weight` x descriptor similarity; dense
    [N, T, D], desc [N, C])."""
    pair = torch.stack([model.pair_scores(dense[i], dense[o]) for i, o in enumerate(nearest)])
    sims = torch.stack([desc[o].float() @ desc[i].float() for i, o in enumerate(nearest)])
    return rerank_score(pair, sims, global_weight)


def descriptor_cosine(models: dict, images: torch.Tensor) -> dict[str, float]:
    """Mean descriptor cosine of each path with fp32 (the timed model's weights)."""
    with torch.inference_mode():
        desc = models["fp32"].encode(images)[1]
        return {
            name: float((desc * m.encode(images)[1]).sum(-1).mean())
            for name, m in models.items()
            if name not in ("fp32", "reference")
        }


def agreement_images(size: int, count: int) -> tuple[torch.Tensor, np.ndarray | None]:
    """`count` demo-world frames spread over its laps (revisits included), preprocessed, and
    their camera positions [count, 2] m (random images and None without the demo world)."""
    from pair_vpr_ros.model import preprocess_batch

    try:
        from pair_vpr_ros.demo.render import render_frame
        from pair_vpr_ros.demo.world import generate_world

        world = generate_world(seed=1234)
        step = max(1, len(world.poses) // count)
        frames = list(range(0, step * count, step))
        rgb = [render_frame(world, i) for i in frames]
        places = world.poses[frames, :2]
    except Exception:  # demo world unavailable: random images
        rgb = [
            np.random.default_rng(i).integers(0, 256, (240, 320, 3), np.uint8)
            for i in range(count)
        ]
        places = None
    return preprocess_batch(rgb, size), places


def default_demo_weights() -> Path | None:
    path = Path(__file__).resolve().parents[1] / "pair_vpr_ros" / "demo" / "assets"
    found = sorted(path.glob("*.pth"))
    return found[0] if found else None


def print_table(rows: list[tuple[str, dict[str, float]]]) -> None:
    names = list(rows[0][1])
    print("| figure | " + " | ".join(f"{n} ms (x fp32)" for n in names) + " |")
    print("|---|" + "---|" * len(names))
    for label, t in rows:
        cells = [f"{t[n]:.1f} ({t[n] / t['fp32']:.2f})" if n in t else "(skipped)" for n in names]
        print(f"| {label} | " + " | ".join(cells) + " |")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
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
        help="model for the agreement check (default: the shipped demo model)",
    )
    p.add_argument(
        "--threads", type=int, default=0,
        help="CPU threads of every pool (model/threads.py; 0: auto for the timed model's size)",
    )  # fmt: skip
    p.add_argument(
        "--batches", default="1,8", help="encode batch sizes, comma-separated (1 comes first)"
    )
    p.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    p.add_argument(
        "--calibration",
        metavar="PATH",
        default="",
        help="also run OpenVINO int8 calibrated on images picked evenly from this rosbag or image "
        "folder (path openvino-calibrated; the node's openvino_calibration parameter)",
    )
    p.add_argument(
        "--calibration-topic",
        metavar="TOPIC",
        help="image topic of a --calibration bag (default: its only one)",
    )
    p.add_argument(
        "--agreement-k",
        type=int,
        default=10,
        help="candidates each agreement query re-ranks (default 10; config/demo.yaml: 5)",
    )
    p.add_argument(
        "--agreement-global-weight",
        type=float,
        default=0.0,
        help="re-rank the agreement queries by pair score + this x descriptor similarity, as the "
        "detector's global_weight does (default 0: the pair score alone; config/demo.yaml: 100)",
    )
    p.add_argument(
        "--agreement-only",
        action="store_true",
        help="skip the timed paths; measure only the agreement with fp32",
    )
    return p.parse_args(argv)


def timed(args: argparse.Namespace, calibration) -> dict:
    """The timed paths (speed, memory, descriptor cosine) of --weights / --arch -> figures."""
    ks = [int(k) for k in args.k.split(",")]
    if args.weights:
        model = load_pairvpr(args.weights, device=args.device, image_size=args.image_size)
    else:
        cfg = ModelConfig.preset(args.arch, image_size=args.image_size)
        model = build_pairvpr(cfg, device=args.device, seed=0)
    apply_threads(resolve_threads(args.threads, model.config))
    size = model.config.image_size
    cpu = platform.processor() or platform.machine()
    print(
        f"# Pair-VPR {model.config.arch}/{size}px on {args.device} ({cpu}, "
        f"{torch.get_num_threads()} threads, torch {torch.__version__})"
    )
    t0 = time.perf_counter()
    models = variants(model, args.device, calibration)
    print(f"building the paths took {time.perf_counter() - t0:.0f} s")
    rows = []
    with torch.inference_mode():
        batches = [int(b) for b in args.batches.split(",")]
        for batch in batches:
            t = interleaved(encode_fns(models, size, args.device, batch), args.repeat, batch)
            rows.append((f"encode, batch {batch} (ms/image)", t))
        for k in ks:
            skip_ref = args.quick and k == max(ks) and len(ks) > 1
            fns = rerank_fns(models, size, args.device, k, not skip_ref)
            # Kernels are warm by now; at large K one pass already averages K candidates.
            t = interleaved(fns, 1 if k >= 50 else args.repeat, k, warmup=False)
            rows.append((f"re-rank K={k} (ms/candidate, both directions)", t))
    print_table(rows)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak resident memory: {peak:.0f} MiB")
    if torch.cuda.is_available() and args.device.startswith("cuda"):
        print(f"peak GPU memory: {torch.cuda.max_memory_allocated() / 2**20:.0f} MiB")
    cos = descriptor_cosine(models, agreement_images(size, 8)[0])
    print(f"descriptor cosine with fp32, {model.config.arch}/{size}px, 8 demo-world images: "
          + ", ".join(f"{n} {c:.5f}" for n, c in cos.items()))  # fmt: skip
    return {
        "paths": {
            name: {"encode_ms": rows[0][1][name], "rerank_ms": rows[len(batches)][1].get(name)}
            for name in models
        },
        "timed_model_cosine": cos,
    }


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.threads:
        apply_threads(args.threads)
    calibration = calibration_loader(args.calibration, args.calibration_topic, warn=print)
    figures = {"agreement": {}} if args.agreement_only else timed(args, calibration)
    weights = args.agreement_weights or default_demo_weights()
    if weights is None:
        print("agreement: skipped (no --agreement-weights and no shipped demo model)")
    else:
        amodel = load_pairvpr(weights)
        images, places = agreement_images(amodel.config.image_size, AGREEMENT_QUERIES)
        figures["agreement"] = agreement(
            variants(amodel, "cpu", calibration),
            images,
            args.agreement_k,
            places,
            args.agreement_global_weight,
        )
        print(f"agreement with fp32 ({Path(weights).name}, {len(images)} demo-world queries x "
              f"{args.agreement_k} candidates, pair score + {args.agreement_global_weight:g} x "
              "similarity):")  # fmt: skip
        for name, a in figures["agreement"].items():
            place = f", same place {a['same_place']:.1%}" if "same_place" in a else ""
            print(f"  {name}: top-1 after re-ranking {a['top1']:.1%}{place}, fp32 score lost at "
                  f"most {a['regret_max']:.4f}, cosine {a['cosine']:.5f}")  # fmt: skip
            for query, gap, moved, *dist in a["flips"]:
                where = f", {dist[0]:.1f} m from fp32's" if dist else ""
                print(f"    query {query}: fp32's top-1 ahead by {gap:.3f}, this path puts the "
                      f"other {moved:.3f} ahead{where}")  # fmt: skip
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
