"""Choose the demo's re-ranking settings on the validation world (issue 24): never on the demo.

Replays a demo-world bag (seed 8 by default: not the demo's seed 7, not a training seed) once
per (top_k, global_weight) with every other setting from config/demo.yaml and the acceptance
threshold off, then reads each run's PR curves: re-ranked (by the detector's re-rank score,
``pair_score + global_weight x global_similarity``) vs global-only, and the threshold that
gives the most recall at precision >= --precision. Prints a Markdown table; pick a row and copy
its top_k, global_weight and threshold into config/demo.yaml.

    python benchmarks/tune_demo_config.py [--weights W.pth] [--bag seed8.mcap]
        [--top-k 5 10] [--global-weight 0 5 10 20 40]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from pair_vpr_ros.demo.bag import write_world_bag
from pair_vpr_ros.demo.world import generate_world
from pair_vpr_ros.offline.replay import run as replay
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.report.loop_truth import LoopEvaluation
from pair_vpr_ros.params.configs import detector_config
from pair_vpr_ros.params.file import read_params_file
from pair_vpr_ros.weights import load_model

ROOT = Path(__file__).parents[1]
DEMO = ROOT / "pair_vpr_ros" / "demo" / "assets" / "demo-small.pth"


def replay_evaluation(bag: Path, out: Path, opts: ReplayOptions, **kwargs) -> LoopEvaluation:
    """Replay ``bag`` and return its evaluation with the whole PR curves."""
    summary = replay.replay_bag(bag, out, opts, **kwargs)
    if summary.error or summary.loop_evaluation is None:
        raise SystemExit(f"error: the replay of {bag} gave no evaluation: {summary.error}")
    return summary.loop_evaluation


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", type=Path, default=DEMO, help="checkpoint (default: the demo's)")
    p.add_argument("--bag", type=Path, help="demo-world bag (default: render --seed)")
    p.add_argument("--seed", type=int, default=8, help="world seed to render (default 8)")
    p.add_argument(
        "--params-file",
        type=Path,
        default=ROOT / "config" / "demo.yaml",
        help="the other detector settings (default config/demo.yaml)",
    )
    p.add_argument("--top-k", type=int, nargs="+", default=[5, 10], help="top_k values")
    p.add_argument(
        "--global-weight",
        type=float,
        nargs="+",
        default=[0, 5, 10, 20, 40],
        help="global_weight values",
    )
    p.add_argument(
        "--global-floor",
        type=float,
        help="global_floor for every run (default: --params-file's; -1 = off)",
    )
    p.add_argument(
        "--precision",
        type=float,
        default=0.97,
        help="operating point: most recall at this precision (default 0.97)",
    )
    args = p.parse_args()
    base = detector_config(read_params_file(args.params_file))
    if args.global_floor is not None:
        base = base.updated(global_floor=args.global_floor)
    model = load_model(args.weights)
    with tempfile.TemporaryDirectory() as tmp:
        bag = args.bag
        if bag is None:
            bag = write_world_bag(generate_world(args.seed, frames=600), Path(tmp) / "val.mcap")
        opts = ReplayOptions(
            topic="/camera/image_raw",
            pose_topic="/odom",
            gt_topic="/ground_truth",
            save_map=False,
            progress=False,
        )
        print(
            f"{bag}: {args.weights.name}; global_floor {base.global_floor:g}; other settings "
            f"from {args.params_file.name}"
        )
        print(
            "| top_k | global_weight | re-ranked AP | global AP | re-ranked R@P90 | "
            f"global R@P90 | threshold @P{args.precision:g} | precision | recall |"
        )
        print("|---" * 9 + "|")
        for k in args.top_k:
            for w in args.global_weight:
                config = base.updated(top_k=k, global_weight=w, score_threshold=-1e6)
                ev = replay_evaluation(
                    bag, Path(tmp) / f"k{k}w{w}", opts, model=model, config=config
                )
                rr, gl = ev.reranked.to_dict(), ev.global_only.to_dict()
                t, prec, rec = ev.reranked.operating_point(args.precision) or (None,) * 3
                fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
                print(
                    f"| {k} | {w:g} | {rr['average_precision']:.3f} | "
                    f"{gl['average_precision']:.3f} | {rr['recall_at_90_precision']:.3f} | "
                    f"{gl['recall_at_90_precision']:.3f} | {fmt(t)} | {fmt(prec)} | "
                    f"{fmt(rec)} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
