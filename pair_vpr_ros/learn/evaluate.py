"""Recall@N of Pair-VPR on retrieval benchmarks: global descriptors only, and after re-ranking the
top-K candidates with the pair classifier (`pairvpr-eval`).

The database goes through the same `PlaceMap` the loop-closure node uses: descriptors in its
FAISS index, dense tokens streamed into its float16 memory-mapped store (so a database larger than
RAM works). Queries are encoded in batches, searched and re-ranked one at a time, then dropped.
A query counts as found at N if any of its first N results is one of its positives; queries
without positives count as misses (reported as ``queries_without_positives``).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from pair_vpr_ros.cli import nonnegative_int, positive_float, positive_int, run_cli
from pair_vpr_ros.detector import Candidate, rank_by_pair_score
from pair_vpr_ros.errors import ConfigError, DatasetError
from pair_vpr_ros.learn.eval_sets import EvalSet, load_eval_set
from pair_vpr_ros.learn.image_files import ImageFiles
from pair_vpr_ros.model import PairVPR
from pair_vpr_ros.pipeline import encode_for_map, map_pair_scores
from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap
from pair_vpr_ros.weights import RANDOM_PREFIX, Weights, resolve_weights
from pair_vpr_ros.weights import load_model as load_weights


@dataclass
class EvalConfig:
    """What to evaluate and how; see ``pairvpr-eval --help``."""

    datasets: list[Path]
    checkpoint: Path | None = None
    random_arch: str | None = None  # random-init model of this preset (smoke tests, no weights)
    image_size: int | None = None  # default: the checkpoint's (322 for released models)
    recall_ns: tuple[int, ...] = (1, 5, 10, 20)
    rerank_k: int = 100  # 0: global descriptors only
    batch_size: int = 16
    workers: int = 2
    device: str = "auto"
    radius_m: float = 25.0
    index: str = "flat"
    work_dir: Path | None = None  # where the temporary dense store lives (default $TMPDIR)
    output_json: Path | None = None
    progress: bool = True


@dataclass
class EvalResult:
    dataset: str
    num_database: int
    num_queries: int
    queries_without_positives: int
    recall_global: dict[int, float]
    recall_rerank: dict[int, float]  # empty when rerank_k == 0
    rerank_k: int
    extract_ms_per_image: float
    search_ms_per_query: float
    rerank_ms_per_query: float
    bytes_per_image: int  # stored per database image: float32 descriptor + float16 dense tokens


def recall_at_n(
    ranked: Sequence[Sequence[int]], positives: Sequence[np.ndarray], ns: Sequence[int]
) -> dict[int, float]:
    """Fraction of queries whose first N results [Q][<=K] contain a positive, for each N."""
    if len(ranked) != len(positives) or not ranked:
        raise ConfigError(f"{len(ranked)} result lists for {len(positives)} queries")
    first_hit = []
    for row, pos in zip(ranked, positives, strict=True):
        hits = np.flatnonzero(np.isin(np.asarray(row, dtype=np.int64), pos))
        first_hit.append(hits[0] if hits.size else np.inf)
    first = np.asarray(first_hit, dtype=np.float64)
    return {int(n): float(np.mean(first < n)) for n in ns}


@dataclass
class StageSeconds:
    """Time spent in each stage of an evaluation."""

    extract: float = 0.0
    search: float = 0.0
    rerank: float = 0.0


def _encoded(
    model: PairVPR, paths: Sequence[Path], cfg: EvalConfig, label: str, spent: StageSeconds
) -> Iterator[tuple[np.ndarray, np.ndarray, list[int]]]:
    """Batches of (dense float16 [B,N,D], descriptors [B,desc_dim], image indices), encoded as
    the node encodes (`pipeline.encode_for_map`)."""
    loader = DataLoader(
        ImageFiles(paths, model.config.image_size),
        batch_size=cfg.batch_size,
        num_workers=cfg.workers,
        pin_memory=model.device.type == "cuda",
    )
    for images, idx in tqdm(loader, disable=not cfg.progress, desc=label):
        t0 = time.perf_counter()
        dense, desc = encode_for_map(model, images)
        spent.extract += time.perf_counter() - t0
        yield dense, desc, idx.tolist()


def fill_map(
    model: PairVPR, data: EvalSet, cfg: EvalConfig, pmap: PlaceMap, spent: StageSeconds
) -> None:
    """Add the database images to ``pmap``; keyframe id i is database image i."""
    for dense, desc, idx in _encoded(model, data.database, cfg, f"{data.name}: database", spent):
        for j, i in enumerate(idx):
            kf = pmap.add(desc[j], dense[j], KeyframeMeta(stamp=float(i), source=data.name))
            assert kf == i, "map ids follow database order"


def rank_queries(
    model: PairVPR, data: EvalSet, cfg: EvalConfig, pmap: PlaceMap, spent: StageSeconds
) -> Iterator[tuple[list[int], list[Candidate]]]:
    """For each query in order: its global ranking (ids) and, when ``cfg.rerank_k > 0``, its
    candidates re-ranked (`rerank`; else an empty list)."""
    k_search = max(cfg.rerank_k, max(cfg.recall_ns))
    for dense, desc, _ in _encoded(model, data.queries, cfg, f"{data.name}: queries", spent):
        for j in range(len(desc)):
            t0 = time.perf_counter()
            hits = pmap.search(desc[j], k_search)
            spent.search += time.perf_counter() - t0
            reranked: list[Candidate] = []
            if cfg.rerank_k > 0:
                t0 = time.perf_counter()
                reranked = rerank(model, pmap, dense[j], hits, cfg.rerank_k)
                spent.rerank += time.perf_counter() - t0
            yield [kf for kf, _ in hits], reranked


def rerank(
    model: PairVPR, pmap: PlaceMap, q_dense: np.ndarray, hits: list[tuple[int, float]], k: int
) -> list[Candidate]:
    """Global hits [(id, similarity)] of one query (dense [N,D] float16) -> its first ``k`` hits
    ordered by pair score exactly as the node orders them (`pipeline.map_pair_scores`, then
    `detector.rank_by_pair_score`), followed by the other hits in global order."""
    cands = [
        Candidate(kf, float("nan"), "", float(sim), rank)
        for rank, (kf, sim) in enumerate(hits, start=1)
    ]
    top, rest = cands[:k], cands[k:]
    if not top:
        return cands
    scores = map_pair_scores(model, pmap, q_dense, [c.id for c in top])
    return rank_by_pair_score(top, scores) + rest


@torch.inference_mode()
def evaluate_set(model: PairVPR, data: EvalSet, cfg: EvalConfig) -> EvalResult:
    """Recall@N of ``model`` on one set (global and re-ranked) with per-stage timings."""
    model.eval()
    shape = (model.num_patches, model.config.embed_dim)
    spent = StageSeconds()
    with PlaceMap(
        model.config.desc_dim, shape, model.fingerprint, cfg.index, work_dir=cfg.work_dir
    ) as pmap:
        fill_map(model, data, cfg, pmap, spent)
        ranked = list(rank_queries(model, data, cfg, pmap, spent))
    ranked_global = [ids for ids, _ in ranked]
    ranked_rerank = [[c.id for c in cands] for _, cands in ranked] if cfg.rerank_k > 0 else []
    n_db, n_q = len(data.database), len(data.queries)
    return EvalResult(
        dataset=data.name,
        num_database=n_db,
        num_queries=n_q,
        queries_without_positives=sum(1 for p in data.positives if p.size == 0),
        recall_global=recall_at_n(ranked_global, data.positives, cfg.recall_ns),
        recall_rerank=(
            recall_at_n(ranked_rerank, data.positives, cfg.recall_ns) if ranked_rerank else {}
        ),
        rerank_k=cfg.rerank_k,
        extract_ms_per_image=1e3 * spent.extract / (n_db + n_q),
        search_ms_per_query=1e3 * spent.search / n_q,
        rerank_ms_per_query=1e3 * spent.rerank / n_q,
        bytes_per_image=model.config.desc_dim * 4 + shape[0] * shape[1] * 2,
    )


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
