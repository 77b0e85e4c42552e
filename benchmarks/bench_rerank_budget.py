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
from pair_vpr_ros.loops.records import rerank_score
from pair_vpr_ros.offline.replay import cli as replay_cli

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "pair_vpr_ros" / "demo" / "assets" / "demo-small.pth"
VARIANTS = {  # name -> (rerank_cascade, learned_floor, first direction)
    "full": (False, False, cascade.FIRST),
    "cascade": (True, True, "query"),
    "cascade, candidate first": (True, True, "candidate"),
    "cascade, no learned floor": (True, False, "query"),
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
    ev, c = summary["evaluation"], summary["config"]
    return {
        "above": {  # records at or above the threshold: what the PR curve there is made of
            r["query_stamp"]: (r["match_id"], r["pair_score"])
            for r in records
            if r["pair_score"] is not None
            and rerank_score(r["pair_score"], r["global_similarity"], c["global_weight"])
            >= c["score_threshold"]
        },
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
    above = set(full["above"]) | set(run["above"])
    same_above = sum(
        q in full["above"] and q in run["above"] and full["above"][q][0] == run["above"][q][0]
        and abs(full["above"][q][1] - run["above"][q][1]) < 1e-3
        for q in above
    )  # fmt: skip
    return {
        "above_threshold": len(above),
        "above_threshold_same": same_above,
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
        names = ["full", *(n for n in args.variants if n != "full")]
        runs = {name: replay(bag, args.work_dir / f"s{seed}-{i}", args.top_k, VARIANTS[name])
                for i, name in enumerate(names)}  # fmt: skip
        rows[seed] = {name: compare(runs["full"], run) for name, run in runs.items()}
        print_world(seed, rows[seed])
    return rows


def print_world(seed: int, rows: dict) -> None:
    print(f"\nseed {seed}{' (demo)' if seed == 7 else ' (validation)'}:")
    print("| run | passes (x full) | per keyframe | same (query, match) | loops | precision | "
          "recall | re-ranked AP | records >= threshold the same | floor skipped (full's "
          "loops among them) |")  # fmt: skip
    print("|---" * 10 + "|")
    for name, r in rows.items():
        print(f"| {name} | {r['passes']:,} ({r['passes_ratio']:.3f}) | "
              f"{r['passes_per_keyframe']:.2f} | {r['same_decision']:.4f} | {r['loops']} | "
              f"{r['precision']:.3f} | {r['recall']:.3f} | {r['ap']:.4f} | "
              f"{r['above_threshold_same']} of {r['above_threshold']} | "
              f"{r['floor_skipped']} ({r['floor_skipped_full_loops']}) |", flush=True)  # fmt: skip
        if r["differ"] and name != "full":
            print(f"  differing keyframes (stamps): {', '.join(f'{q:.2f}' for q in r['differ'])}")


def new_ground(args: argparse.Namespace) -> dict:
    """Part 1b, where the learned floor can pay: the demo world's drive, then (stamps shifted to
    follow on) the drive of world `--new-ground`, new ground after 400 revisits whose own
    second and third laps are loops again. The pipeline as the replay runs it (config/demo.yaml,
    SIFT, depth), full scoring against the cascade with and without the learned floor."""
    from dataclasses import replace

    from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
    from pair_vpr_ros.offline.bags.sources import FrameCounts, source_frames
    from pair_vpr_ros.params.configs import detector_config, geometry_config
    from pair_vpr_ros.params.file import read_params_file
    from pair_vpr_ros.weights import load_model

    values = read_params_file(ROOT / "config" / "demo.yaml")
    geometry = replace(geometry_config(values), features="sift")
    bags = [world_bag(args.work_dir, 7), world_bag(args.work_dir, args.new_ground)]
    model, runs = load_model(DEMO), {}
    for name in ("full", "cascade", "cascade, no learned floor"):
        on, floor, _ = VARIANTS[name]
        config = detector_config(values).updated(
            top_k=args.top_k, rerank_cascade=on, learned_floor=floor
        )
        pipe, accepted, shift = LoopClosurePipeline(model, config, geometry=geometry), {}, 0.0
        for i, bag in enumerate(bags):
            last = 0.0
            for frame in source_frames(
                bag, FrameCounts(), "/camera/image_raw", pose_topic="/odom"
            ):
                frame.stamp += shift
                last = frame.stamp
                loop = pipe.process(frame).loop
                if loop is not None:
                    accepted[(i, loop.query_stamp)] = loop.match_id if loop.accepted else None
            shift = last + 100.0 - 1_700_000_000.0  # the next drive starts 100 s later
        runs[name] = {"accepted": accepted, "counts": pipe.counts.to_dict()}
        pipe.close()
    rows = {}
    for name, run in runs.items():
        full, queries = runs["full"]["accepted"], sorted(run["accepted"])
        later = [q for q in queries if q[0] == 1]
        rows[name] = {
            "passes": run["counts"]["decoder_passes"],
            "passes_ratio": run["counts"]["decoder_passes"]
            / runs["full"]["counts"]["decoder_passes"],
            "same_decision": sum(full.get(q) == run["accepted"][q] for q in queries)
            / len(queries),
            "loops_new_ground": sum(run["accepted"][q] is not None for q in later),
            "skipped": run["counts"]["rerank_skipped"],
        }
        r = rows[name]
        print(f"new ground (seed 7, then {args.new_ground}), {name}: passes {r['passes']:,} "
              f"({r['passes_ratio']:.3f}), same (query, match) {r['same_decision']:.4f}, "
              f"loops on the new ground {r['loops_new_ground']}, skipped by the floor "
              f"{r['skipped']}", flush=True)  # fmt: skip
    return rows


def vitb_costs(args: argparse.Namespace) -> dict:
    """ms per decoder pass of each re-rank graph, ViT-B/322 random weights, OpenVINO int8: every
    chunk size's model built (or read from the cache) first, then timed in turn, round by
    round, so that the machine's load falls on all of them alike."""
    from pair_vpr_ros.model import ModelConfig, build_pairvpr, save_pairvpr
    from pair_vpr_ros.model.openvino_backend import OpenVINOModel
    from pair_vpr_ros.weights import load_model

    checkpoint = args.work_dir / "vitb-random.pth"
    if not checkpoint.exists():
        save_pairvpr(build_pairvpr(ModelConfig(), seed=0), checkpoint)
    out, fns = {}, {}
    for chunk in args.chunks:
        t0 = time.perf_counter()
        model = OpenVINOModel(load_model(str(checkpoint)), "int8", chunk=chunk,
                              cache_dir=args.work_dir / "ovcache")  # fmt: skip
        out[chunk] = {"start_s": time.perf_counter() - t0, "from_cache": model.from_cache}
        fns[chunk], out[chunk]["one_way_sum_vs_both_max_abs"] = graph_calls(model, chunk)
    times = {(chunk, name): [] for chunk in fns for name in fns[chunk]}
    for _ in range(args.repeat):
        for chunk, calls in fns.items():
            for name, (fn, _) in calls.items():
                t = time.perf_counter()
                fn()
                times[chunk, name].append((time.perf_counter() - t) * 1e3)
    for chunk, calls in fns.items():
        per = {name: float(np.median(times[chunk, name])) / n for name, (_, n) in calls.items()}
        out[chunk]["ms_per_pass"] = per
        print(
            f"chunk {chunk}: ms per pass {json.dumps({k: round(v, 1) for k, v in per.items()})}"
            f" (start {out[chunk]['start_s']:.0f} s, cache {out[chunk]['from_cache']}); one-way "
            f"sum vs both: max |d| {out[chunk]['one_way_sum_vs_both_max_abs']:.2e}",
            flush=True,
        )
    return out


def graph_calls(model, chunk: int) -> tuple[dict, float]:
    """{graph: (call, decoder passes it runs)} on random tokens (the query side: per query,
    counted once), after one warm-up call each; and the largest difference between the sum of
    the one-direction graphs and the two-direction graph on them."""
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
    for fn, _ in fns.values():
        fn()
    both = scorer.logits(c, "query") + scorer.logits(c, "candidate")
    return fns, float((both - scorer.scores(c)).abs().max())


def within_budget(costs: dict, budget_ms: float, top_k: int) -> dict:
    """Candidates scored within `budget_ms` at these costs, by the detector's budget rule (the
    first step always runs; then a step while the time spent plus its predicted cost, this
    keyframe's mean per pass so far, fits): full scoring (`chunk` candidates both ways a step)
    against the cascade with every candidate a contender (random weights: all near-ties), the
    global best both ways, then one direction of one candidate a step (query first)."""
    out = {}
    for chunk, c in costs.items():
        ms = c["ms_per_pass"]
        full = budget_steps([2 * chunk * ms["both"]] * -(-top_k // chunk), ms["query side"],
                            [2 * chunk] * top_k, budget_ms, 1)  # fmt: skip
        steps = [ms["query first"]] * (top_k + 1)
        cascade = budget_steps(steps, ms["query side"], [1] * len(steps), budget_ms, 2)
        out[chunk] = {
            "full_scored": min(top_k, chunk * full),
            "cascade_one_way_at_least": min(top_k, cascade - 1),
        }
        print(
            f"chunk {chunk}, {budget_ms:g} ms: full scoring scores {out[chunk]['full_scored']} "
            f"of {top_k}; the cascade gives {out[chunk]['cascade_one_way_at_least']} at least "
            f"one direction",
            flush=True,
        )
    return out


def budget_steps(
    step_ms: list[float], start_ms: float, passes: list[int], budget: float, always: int
) -> int:
    """How many of the steps (each `step_ms`, `passes` passes; the first `always` run
    unchecked) run within `budget`."""
    spent, done = start_ms, 0
    for i, cost in enumerate(step_ms):
        if i >= always and spent + spent / sum(passes[:i]) * passes[i] > budget:
            break
        spent, done = spent + cost, i + 1
    return done


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work-dir", type=Path, required=True, help="bags, runs and the cache")
    p.add_argument("--seeds", type=int, nargs="*", default=[7, 8, 9], help="worlds (7 8 9)")
    p.add_argument("--top-k", type=int, default=10, help="candidates per keyframe (10)")
    p.add_argument(
        "--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS),
        help="runs against full scoring (default: all)",
    )  # fmt: skip
    p.add_argument(
        "--new-ground", type=int, metavar="SEED",
        help="also part 1b: the demo drive, then world SEED's (e.g. 10)",
    )  # fmt: skip
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
    if args.new_ground is not None:
        result["new_ground"] = new_ground(args)
    if args.vitb:
        result["vitb"] = vitb_costs(args)
        result["budget"] = within_budget(result["vitb"], args.budget_ms, args.top_k)
    print(f"load {os.getloadavg()[0]:.1f}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
