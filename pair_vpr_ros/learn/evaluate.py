"""Recall@N of Pair-VPR on retrieval benchmarks: global descriptors only, and after re-ranking the
top-K candidates with the pair classifier (`pairvpr-eval`).

The database goes through the same `PlaceMap` the loop-closure node uses: descriptors in its
FAISS index, dense tokens streamed into its float16 memory-mapped store (so a database larger than
RAM works). Queries are encoded in batches, searched and re-ranked one at a time, then dropped.
A query counts as found at N if any of its first N results is one of its positives; queries
without positives count as misses (reported as ``queries_without_positives``).

The measurement of one set lives in ``recall`` (``EvalConfig``, ``EvalResult``, ``evaluate_set``
and its stages); this module is the tool (weights, all sets, JSON, table, ``main``).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path

import torch

from pair_vpr_ros.cli import (
    nonnegative_float,
    nonnegative_int,
    positive_float,
    positive_int,
    run_cli,
)
from pair_vpr_ros.errors import ConfigError, DatasetError
from pair_vpr_ros.learn.eval_sets import load_eval_set
from pair_vpr_ros.learn.recall import EvalConfig, EvalResult, evaluate_set
from pair_vpr_ros.weights import RANDOM_PREFIX, Weights, resolve_weights
from pair_vpr_ros.weights import load_model as load_weights


def eval_weights(cfg: EvalConfig) -> Weights:
    """--random-init, else --weights, else found as the node and the replay find them
    (``weights.resolve_weights``: $PAIRVPR_WEIGHTS, the per-user folder; a ``CheckpointError``
    names every place looked in)."""
    if cfg.random_arch is not None:
        return Weights(RANDOM_PREFIX + cfg.random_arch, "--random-init")
    if cfg.checkpoint is not None:
        return Weights(str(cfg.checkpoint), "--weights")
    return resolve_weights(None, params_rule=False)


def load_model(cfg: EvalConfig, found: Weights | None = None) -> torch.nn.Module:
    """The network `cfg` names (``eval_weights``), on its device."""
    found = found or eval_weights(cfg)
    return load_weights(found, device=cfg.device, image_size=cfg.image_size)


def run_evaluation(cfg: EvalConfig) -> list[EvalResult]:
    """Load the sets (all checked before the model loads), evaluate, write JSON if asked."""
    if not cfg.datasets:
        raise ConfigError("no evaluation dataset given")
    if cfg.rerank_k < 0 or not cfg.recall_ns or min(cfg.recall_ns) < 1:
        raise ConfigError(
            f"need rerank_k >= 0 and recall N >= 1, got {cfg.rerank_k}, {cfg.recall_ns}"
        )
    if not (math.isfinite(cfg.global_weight) and cfg.global_weight >= 0):
        raise ConfigError(f"global_weight must be a finite number >= 0, got {cfg.global_weight}")
    sets = [load_eval_set(root, cfg.radius_m) for root in cfg.datasets]
    found = eval_weights(cfg)
    model = load_model(cfg, found)
    results = [evaluate_set(model, s, cfg) for s in sets]
    if cfg.output_json is not None:
        payload = {
            "checkpoint": found.value.replace(RANDOM_PREFIX, "random:", 1)
            if found.value.startswith(RANDOM_PREFIX)
            else found.value,
            "fingerprint": model.fingerprint,
            "results": [asdict(r) for r in results],
        }
        try:
            cfg.output_json.parent.mkdir(parents=True, exist_ok=True)
            cfg.output_json.write_text(json.dumps(payload, indent=2) + "\n", encoding="utf-8")
        except OSError as err:
            raise DatasetError(f"cannot write results to {cfg.output_json}: {err}") from err
    return results


def format_table(results: Sequence[EvalResult]) -> str:
    """Plain-text table: recalls in percent, timings in ms, storage in KiB per image."""
    if not results:
        return ""
    ns = list(results[0].recall_global)
    head = ["dataset", "db", "queries", *[f"R@{n}" for n in ns]]
    head += [f"rr R@{n}" for n in ns] + ["extract ms/img", "search ms/q", "rerank ms/q", "KiB/img"]
    rows = [head]
    for r in results:
        rerank = [f"{100 * r.recall_rerank[n]:.1f}" if r.recall_rerank else "-" for n in ns]
        rows.append(
            [
                r.dataset,
                str(r.num_database),
                str(r.num_queries),
                *[f"{100 * r.recall_global[n]:.1f}" for n in ns],
                *rerank,
                f"{r.extract_ms_per_image:.1f}",
                f"{r.search_ms_per_query:.2f}",
                f"{r.rerank_ms_per_query:.1f}",
                f"{r.bytes_per_image / 1024:.1f}",
            ]
        )
    widths = [max(len(row[c]) for row in rows) for c in range(len(head))]
    return "\n".join(
        "  ".join(v.rjust(w) for v, w in zip(row, widths, strict=True)) for row in rows
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pairvpr-eval",
        description="Recall@N of Pair-VPR (global and re-ranked) on database/ + queries/ sets",
    )
    p.add_argument(
        "datasets",
        nargs="+",
        type=Path,
        help="dataset roots: ROOT/database and ROOT/queries image folders, ground "
        "truth from ROOT/ground_truth.npy or @easting@northing@ file names",
    )
    p.add_argument(
        "--weights",
        "--checkpoint",
        dest="checkpoint",
        type=Path,
        help="Pair-VPR weights (e.g. pairvpr-vitB.pth); default: $PAIRVPR_WEIGHTS, else the one "
        ".pth in $XDG_DATA_HOME/pair_vpr_ros/ (docs/install.md, 'Released weights')",
    )
    p.add_argument(
        "--random-init",
        metavar="ARCH",
        help="evaluate a random-init model of this "
        "preset instead of a checkpoint (pipeline smoke test; recalls are meaningless)",
    )
    p.add_argument(
        "--image-size", type=positive_int, help="input size (default: the checkpoint's)"
    )
    p.add_argument(
        "--recall",
        type=positive_int,
        nargs="+",
        default=[1, 5, 10, 20],
        metavar="N",
        help="report Recall@N for these N (default 1 5 10 20)",
    )
    p.add_argument(
        "--rerank-k",
        type=nonnegative_int,
        default=100,
        help="re-rank this many global candidates, 0 = global only (default 100)",
    )
    p.add_argument(
        "--global-weight",
        type=nonnegative_float,
        default=0.0,
        help="re-rank by pair score + this x global similarity, the node's global_weight "
        "parameter (default 0: the pair score alone, as the paper)",
    )
    p.add_argument(
        "--radius",
        type=positive_float,
        default=25.0,
        help="positives lie within this many metres (UTM ground truth, default 25)",
    )
    p.add_argument("--batch-size", type=positive_int, default=16, help="images per encoder batch")
    p.add_argument(
        "--workers", type=nonnegative_int, default=2, help="image loading worker processes"
    )
    p.add_argument("--device", default="auto", help="auto, cuda or cpu (default auto)")
    p.add_argument(
        "--index",
        default="flat",
        choices=("flat", "hnsw", "ivf"),
        help="FAISS index of the map: exact flat, or approximate ivf (trained lists, exact "
        "below 25,000 images) or hnsw (default flat)",
    )
    p.add_argument(
        "--work-dir",
        type=Path,
        help="folder for the temporary dense-token store (default $TMPDIR)",
    )
    p.add_argument("--json", type=Path, dest="output_json", help="also write results as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def _run(args: argparse.Namespace) -> None:
    cfg = EvalConfig(
        datasets=args.datasets,
        checkpoint=args.checkpoint,
        random_arch=args.random_init,
        image_size=args.image_size,
        recall_ns=tuple(args.recall),
        rerank_k=args.rerank_k,
        global_weight=args.global_weight,
        batch_size=args.batch_size,
        workers=args.workers,
        device=args.device,
        radius_m=args.radius,
        index=args.index,
        work_dir=args.work_dir,
        output_json=args.output_json,
        progress=not args.quiet,
    )
    print(format_table(run_evaluation(cfg)))


def main(argv: list[str] | None = None) -> int:
    """Exit codes: ``pair_vpr_ros.cli`` (0 done, 1 error or bad data, 2 usage, 130 Ctrl-C)."""
    return run_cli(build_parser(), _run, argv)


if __name__ == "__main__":
    raise SystemExit(main())
