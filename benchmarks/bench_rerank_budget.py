"""The re-rank cascade against full scoring (issue 46): decoder passes and decisions.

Part 1, decisions (the shipped demo model: its score distributions are real). Each world's
600-frame bag (seed 7: the demo; 8 and 9: validation worlds, rendered into --work-dir when
missing, as `pairvpr-make-demo-bag --seed S --frames 600`) is replayed as `make demo` replays
it (config/demo.yaml, relative poses from depth), at --top-k, once with full scoring
(`rerank_cascade: false`) and once per cascade variant. Reported per world and variant: decoder
passes (one direction of one pair = 1) against full scoring's, keyframes whose accepted
(query, match) is the same as full scoring's (a rejected keyframe: "none" on both sides),
precision / recall / re-ranked AP from the replay's evaluation, and the keyframes the learned
floor skipped with the full-scoring loops among them (true ones: the recall it cost).

The re-ranked AP of a cascade run ranks each keyframe's record by its score, as every replay
does; the cascade's records carry full two-direction scores only (a rejected keyframe's record
is its best candidate scored both ways, the global best at least), so the PR curve is full
scoring's at and above score_threshold and can sit lower below it.

Part 2, ViT-B cost (--vitb; random weights, OpenVINO int8, the node's back end on a CPU): ms
per decoder pass of each re-rank graph (both directions, query first, candidate first) at each
--chunks size (export and calibration are cached in --work-dir/ovcache), and what an
800 ms budget buys at top_k 10: candidates with at least one direction scored, full scoring
against the cascade.

    python benchmarks/bench_rerank_budget.py --work-dir /var/tmp/rr [--seeds 7 8 9] [--top-k 10]
    python benchmarks/bench_rerank_budget.py --work-dir /var/tmp/rr --seeds --vitb --chunks 1 2 4
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from pair_vpr_ros.demo import make_bag
from pair_vpr_ros.loops import cascade
from pair_vpr_ros.offline.replay import cli as replay_cli

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "pair_vpr_ros" / "demo" / "assets" / "demo-small.pth"
VARIANTS = {  # name -> (rerank_cascade, learned_floor, first direction)
    "full": (False, False, cascade.FIRST),
    "cascade": (True, True, "candidate"),
    "cascade, query first": (True, True, "query"),
    "cascade, no learned floor": (True, False, "candidate"),
}


def world_bag(work: Path, seed: int) -> Path:
    bag = work / f"seed{seed}.mcap"
    if not bag.exists():
        make_bag.main([str(bag), "--seed", str(seed), "--frames", "600", "--force"])
    return bag


def replay(bag: Path, out: Path, top_k: int, variant: tuple[bool, bool, str]) -> dict:
    """One replay of `bag` as make demo runs it, at `top_k`, with the variant's settings."""
    on, floor, first = variant
    values = yaml.safe_load((ROOT / "config" / "demo.yaml").read_text())
    values["/**"]["ros__parameters"].update(rerank_cascade=on, learned_floor=floor)
    out.mkdir(parents=True, exist_ok=True)
    params = out / "params.yaml"
    params.write_text(yaml.safe_dump(values))
    cascade.FIRST, cascade.SECOND = first, "query" if first == "candidate" else "candidate"
    argv = [str(bag), "--topic", "/camera/image_raw", "--weights", str(DEMO),
            "--params-file", str(params), "--pose-topic", "/odom", "--gt-topic",
            "/ground_truth", "--out", str(out / "replay"), "--overwrite", "--quiet",
            "--map-dir", "none", "--top-k", str(top_k)]  # fmt: skip
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):
        status = replay_cli.main(argv)
    if status != 0:
        raise SystemExit(f"error: the replay of {bag} failed (status {status}), see {out}")
    records = json.loads((out / "replay" / "loops.json").read_text())
    summary = json.loads((out / "replay" / "summary.json").read_text())
    ev = summary["evaluation"]
    return {
        "seconds": time.perf_counter() - t0,
        "accepted": {r["query_stamp"]: r["match_id"] if r["accepted"] else None for r in records},
        "skipped": {r["query_stamp"] for r in records if r["reason"].startswith("below learned")},
        "counts": summary["pipeline_counts"],
        "loops": summary["loops"],
        "precision": ev["precision"],
        "recall": ev["recall"],
        "ap": ev["reranked"]["average_precision"],
    }


def compare(full: dict, run: dict) -> dict:
    """`run`'s figures against full scoring's."""
    queries = sorted(set(full["accepted"]) | set(run["accepted"]))
    same = sum(full["accepted"].get(q) == run["accepted"].get(q) for q in queries)
    lost = [q for q in run["skipped"] if full["accepted"].get(q) is not None]
    passes, base = run["counts"]["decoder_passes"], full["counts"]["decoder_passes"]
    return {
        "keyframes": len(queries),
        "passes": passes,
        "passes_ratio": passes / base if base else None,
        "passes_per_keyframe": passes / max(len(queries), 1),
        "same_decision": same / max(len(queries), 1),
        "differ": [q for q in queries if full["accepted"].get(q) != run["accepted"].get(q)],
        "floor_skipped": run["counts"].get("rerank_skipped", 0),
        "floor_skipped_full_loops": len(lost),
        **{k: run[k] for k in ("loops", "precision", "recall", "ap", "seconds")},
    }


def decisions(args: argparse.Namespace) -> dict:
    rows = {}
    for seed in args.seeds:
        bag = world_bag(args.work_dir, seed)
        runs = {name: replay(bag, args.work_dir / f"s{seed}-{i}", args.top_k, variant)
                for i, (name, variant) in enumerate(VARIANTS.items())}  # fmt: skip
        rows[seed] = {name: compare(runs["full"], run) for name, run in runs.items()}
        print_world(seed, rows[seed])
    return rows


def print_world(seed: int, rows: dict) -> None:
    print(f"\nseed {seed}{' (demo)' if seed == 7 else ' (validation)'}:")
    print("| run | passes (x full) | per keyframe | same (query, match) | loops | precision | "
          "recall | re-ranked AP | floor skipped (full's loops among them) |")  # fmt: skip
    print("|---" * 9 + "|")
    for name, r in rows.items():
        print(f"| {name} | {r['passes']:,} ({r['passes_ratio']:.3f}) | "
              f"{r['passes_per_keyframe']:.2f} | {r['same_decision']:.4f} | {r['loops']} | "
              f"{r['precision']:.3f} | {r['recall']:.3f} | {r['ap']:.4f} | "
              f"{r['floor_skipped']} ({r['floor_skipped_full_loops']}) |", flush=True)  # fmt: skip
        if r["differ"] and name != "full":
            print(f"  differing keyframes (stamps): {', '.join(f'{q:.2f}' for q in r['differ'])}")


def vitb_costs(args: argparse.Namespace) -> dict:
    """ms per decoder pass of each re-rank graph, ViT-B/322 random weights, OpenVINO int8."""
    from pair_vpr_ros.model import ModelConfig, build_pairvpr, save_pairvpr
    from pair_vpr_ros.model.openvino_backend import OpenVINOModel
    from pair_vpr_ros.weights import load_model

    checkpoint = args.work_dir / "vitb-random.pth"
    if not checkpoint.exists():
        save_pairvpr(build_pairvpr(ModelConfig(), seed=0), checkpoint)
    out = {}
    for chunk in args.chunks:
        t0 = time.perf_counter()
        model = OpenVINOModel(load_model(str(checkpoint)), "int8", chunk=chunk,
                              cache_dir=args.work_dir / "ovcache")  # fmt: skip
        out[chunk] = {"start_s": time.perf_counter() - t0, "from_cache": model.from_cache}
        out[chunk].update(time_graphs(model, chunk, args.repeat))
        per = out[chunk]["ms_per_pass"]
        print(
            f"chunk {chunk}: ms per pass {json.dumps({k: round(v, 1) for k, v in per.items()})}"
            f" (start {out[chunk]['start_s']:.0f} s, cache {model.from_cache}); one-way sum "
            f"vs both: max |d| {out[chunk]['one_way_sum_vs_both_max_abs']:.2e}",
            flush=True,
        )
    return out


def time_graphs(model, chunk: int, repeat: int) -> dict:
    """Median ms per decoder pass of each re-rank graph (the query side: per query), in turn."""
    import torch

    g = torch.Generator().manual_seed(0)
    q = torch.randn(model.num_patches, model.config.embed_dim, generator=g)
    c = torch.randn(chunk, model.num_patches, model.config.embed_dim, generator=g)
    scorer = model.query_scorer(q)
    fns = {
        "query side": (lambda: model.query_scorer(q), 1),
        "both": (lambda: scorer.scores(c), 2 * chunk),
        "query first": (lambda: scorer.logits(c, "query"), chunk),
        "candidate first": (lambda: scorer.logits(c, "candidate"), chunk),
    }
    times = {name: [] for name in fns}
    for fn, _ in fns.values():
        fn()
    for _ in range(repeat):
        for name, (fn, _) in fns.items():
            t = time.perf_counter()
            fn()
            times[name].append((time.perf_counter() - t) * 1e3)
    both = scorer.logits(c, "query") + scorer.logits(c, "candidate")
    return {
        "ms_per_pass": {name: float(np.median(times[name])) / n for name, (_, n) in fns.items()},
        "one_way_sum_vs_both_max_abs": float((both - scorer.scores(c)).abs().max()),
    }


def within_budget(costs: dict, budget_ms: float, top_k: int) -> dict:
    """Candidates with at least one direction scored within `budget_ms` (the first step always
    runs, then whole chunks while they fit), full scoring against the cascade (the first chunk
    both ways, then the first direction of the others), from the measured costs."""
    out = {}
    for chunk, c in costs.items():
        both = 2 * chunk * c["ms_per_pass"]["both"]
        one = chunk * c["ms_per_pass"]["candidate first"]
        q = c["ms_per_pass"]["query side"]
        full = chunk * (1 + max(0, int((budget_ms - q - both) // both)))
        cas = chunk + chunk * max(0, int((budget_ms - q - 2 * one) // one))
        out[chunk] = {"full": min(full, top_k), "cascade": min(cas, top_k)}
        print(
            f"chunk {chunk}, {budget_ms:g} ms: candidates with a score, full "
            f"{out[chunk]['full']}, cascade (one direction at least) {out[chunk]['cascade']} "
            f"of {top_k}"
        )
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work-dir", type=Path, required=True, help="bags, runs and the cache")
    p.add_argument("--seeds", type=int, nargs="*", default=[7, 8, 9], help="worlds (7 8 9)")
    p.add_argument("--top-k", type=int, default=10, help="candidates per keyframe (10)")
    p.add_argument("--vitb", action="store_true", help="also part 2: ViT-B OpenVINO int8 cost")
    p.add_argument("--chunks", type=int, nargs="+", default=[2], help="re-rank chunk sizes")
    p.add_argument("--budget-ms", type=float, default=800.0, help="part 2's budget (800)")
    p.add_argument("--repeat", type=int, default=5, help="timed calls per graph (5)")
    p.add_argument("--json", type=Path, help="write every figure here")
    args = p.parse_args(argv)
    args.work_dir.mkdir(parents=True, exist_ok=True)
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.processor() or ''} "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f}")  # fmt: skip
    result = {"decisions": decisions(args) if args.seeds else {}}
    if args.vitb:
        result["vitb"] = vitb_costs(args)
        result["budget"] = within_budget(result["vitb"], args.budget_ms, args.top_k)
    print(f"load {os.getloadavg()[0]:.1f}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
