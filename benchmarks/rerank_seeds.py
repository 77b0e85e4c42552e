"""Re-ranked vs global-only ranking on several demo worlds, each and pooled (issue 24).

One world's AP moves by a few hundredths with a handful of queries (seed 8's false loops at
the top are matches 10.5-16 m away, just past the 10 m radius), so the demo model's drive stage
and `global_weight` are judged on worlds 8-12 pooled. Renders each world's 600-frame drive (in
grey with --mono, as `pairvpr-make-demo-bag --mono`), runs it through the pipeline with
config/demo.yaml's exclusion, keeping every keyframe's global top max(--top-k) with pair scores
(threshold and geometric verification off), then scores each query's best candidate offline for
every (K, w): re-ranked = best of pair + w x similarity among the top K, global = top 1 by
similarity. A match is true within 10 m and 8 s apart (the replay report's rule); recall counts
the keyframes that have a true match. Prints a Markdown table: AP and recall at precision 0.9.

    python benchmarks/rerank_seeds.py [--weights W.pth] [--seeds 8 9 10 11 12] [--mono]
        [--top-k 5] [--global-weight 0 50 100 200]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from pair_vpr_ros.demo import generate_world, render_frame
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.records import rerank_score
from pair_vpr_ros.offline.report.loop_truth import (
    KeyframeInfo,
    PRCurve,
    is_true_loop,
    pr_curve,
    queries_with_true_match,
)
from pair_vpr_ros.params.configs import detector_config
from pair_vpr_ros.params.file import read_params_file
from pair_vpr_ros.weights import load_model

ROOT = Path(__file__).parents[1]
DEMO = ROOT / "pair_vpr_ros" / "demo" / "assets" / "demo-small.pth"
GT_RADIUS, EXCLUSION_S = 10.0, 8.0


def world_queries(model, seed: int, top_k: int, mono: bool) -> tuple[list, int]:
    """-> per query keyframe: [K, 3] rows (similarity, pair score, true), global order; and the
    number of keyframes with a true match."""
    config = detector_config(read_params_file(ROOT / "config" / "demo.yaml"))
    config = config.updated(top_k=top_k, score_threshold=-1e6, geometric_verification=False)
    world = generate_world(seed, frames=600)
    pipe = LoopClosurePipeline(model, config)
    infos, rows = {}, []
    for i in tqdm(range(len(world.poses)), desc=f"seed {seed}", leave=False):
        rgb = render_frame(world, i)
        if mono:
            rgb = cv2.cvtColor(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
        stamp = world.stamps_ns[i] * 1e-9
        outcome = pipe.process(Frame(stamp, rgb))
        if outcome.keyframe_id is None:
            continue
        x, y, _ = world.poses[i]
        info = KeyframeInfo(outcome.keyframe_id, stamp, (x, y, 0.0, 0.0, 0.0, 0.0, 1.0))
        infos[info.id] = info
        cands = outcome.candidates or []
        if cands:
            rows.append((info, [(infos[c.id], c.global_similarity, c.pair_score) for c in cands]))
    pipe.close()
    queries = []
    for query, cands in rows:
        table = [
            (sim, pair, is_true_loop(query, match, GT_RADIUS, EXCLUSION_S))
            for match, sim, pair in cands
        ]
        queries.append(np.array(table, dtype=np.float64))
    positives = len(queries_with_true_match(list(infos.values()), GT_RADIUS, EXCLUSION_S))
    return queries, positives


def curve(queries: list[np.ndarray], positives: int, k: int, w: float | None) -> PRCurve:
    """PR of each query's kept candidate: global top 1 (w None) or best pair + w x similarity
    among the top k."""
    scores, hits = [], []
    for q in queries:
        if w is None:
            best, score = 0, q[0, 0]
        else:
            fused = rerank_score(q[:k, 1], q[:k, 0], w)
            best = int(np.argmax(fused))
            score = fused[best]
        scores.append(score)
        hits.append(bool(q[best, 2]))
    return pr_curve(scores, hits, positives)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", type=Path, default=DEMO, help="checkpoint (default: the demo's)")
    p.add_argument("--seeds", type=int, nargs="+", default=[8, 9, 10, 11, 12], help="worlds")
    p.add_argument("--mono", action="store_true", help="grey frames, as a mono8 camera")
    p.add_argument("--top-k", type=int, nargs="+", default=[5], help="top_k values")
    p.add_argument(
        "--global-weight", type=float, nargs="+", default=[0, 50, 100, 200], help="w values"
    )
    args = p.parse_args()
    model = load_model(args.weights)
    worlds = {s: world_queries(model, s, max(args.top_k), args.mono) for s in args.seeds}
    pooled = ([q for qs, _ in worlds.values() for q in qs], sum(n for _, n in worlds.values()))
    groups = [(f"seed {s}", *worlds[s]) for s in args.seeds]
    groups.append(("pooled " + " ".join(map(str, args.seeds)), *pooled))
    print(f"{args.weights.name}, {'mono8' if args.mono else 'colour'}: AP / recall at P 0.9")
    heads = [f"K={k}, w={w:g}" for k in args.top_k for w in args.global_weight]
    print("| worlds | global only | " + " | ".join(heads) + " |")
    print("|---" * (len(heads) + 2) + "|")
    for name, queries, positives in groups:
        cells = [curve(queries, positives, 1, None)]
        cells += [curve(queries, positives, k, w) for k in args.top_k for w in args.global_weight]
        text = [f"{c.average_precision():.3f} / {c.recall_at_precision(0.9):.3f}" for c in cells]
        print(f"| {name} | " + " | ".join(text) + " |", flush=True)


if __name__ == "__main__":
    main()
