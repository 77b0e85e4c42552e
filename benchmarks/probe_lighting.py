"""Does the pair score predict "same lighting" instead of "same place"? (issue 24, point 1)

On a held-out place dataset (each place rendered in day / dusk / overcast: view k.png in lighting
k mod 3), every third view is a query; the global descriptor gives K candidates, the pair score
re-ranks them. Prints global vs re-ranked AP, recall at precision 0.9 and R@1; the lighting AUC
(on candidates of *other* places: how well the score tells a candidate in the query's lighting
from one in another; 0.5 = no lighting shortcut); and the identical-pair check (a view against
itself vs its best true revisit among the candidates).

    python benchmarks/probe_lighting.py [--weights W.pth ...] [--data ROOT | --seed 201]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from pair_vpr_ros.demo.dataset import write_place_dataset
from pair_vpr_ros.learn.heldout import HeldoutViews, measure
from pair_vpr_ros.model import load_pairvpr

DEMO = Path(__file__).parents[1] / "pair_vpr_ros" / "demo" / "assets" / "demo-small.pth"
COLUMNS = (
    "global_ap",
    "rerank_ap",
    "global_r@p90",
    "rerank_r@p90",
    "global_r@1",
    "rerank_r@1",
    "lighting_auc",
    "lighting_auc_global",
    "identical_score",
    "revisit_score",
    "identical_ge_revisit",
)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", type=Path, nargs="+", default=[DEMO], help="checkpoints")
    p.add_argument("--data", type=Path, help="place folders (default: render --seed)")
    p.add_argument("--seed", type=int, default=201, help="world seed to render (default 201)")
    p.add_argument("--places", type=int, default=60, help="places to render (default 60)")
    p.add_argument("-k", type=int, default=10, help="candidates re-ranked (default 10)")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = args.data
        if root is None:
            root = write_place_dataset(
                Path(tmp) / f"world{args.seed}", args.seed, args.places, 6, (160, 120)
            )
        views = HeldoutViews.load(root)
        print(f"{root}: {len(views.paths)} views, {len(views.queries)} queries, K={args.k}")
        print("| weights | " + " | ".join(COLUMNS) + " |")
        print("|---" * (len(COLUMNS) + 1) + "|")
        for w in args.weights:
            got = measure(load_pairvpr(w), views, args.k)
            print(f"| {w.name} | " + " | ".join(f"{got[c]:.3f}" for c in COLUMNS) + " |")


if __name__ == "__main__":
    main()
