"""Recall@N of one evaluation set: the database into a `PlaceMap`, queries searched and re-ranked.

Global ranking and re-ranking follow the node exactly (`pipeline.encode_for_map`,
`pipeline.map_pair_scores`, `detector.rank_by_pair_score`); the tool around it is
:mod:`pair_vpr_ros.learn.evaluate` (``pairvpr-eval``).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.learn.eval_sets import EvalSet
from pair_vpr_ros.learn.image_files import ImageFiles
from pair_vpr_ros.loops.records import Candidate, rank_by_pair_score
from pair_vpr_ros.loops.scoring import encode_for_map, map_pair_scores
from pair_vpr_ros.model import PairVPR
from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap


@dataclass
class EvalConfig:
    """What to evaluate and how; see ``pairvpr-eval --help``."""

    datasets: list[Path]
    checkpoint: Path | None = None
    random_arch: str | None = None  # random-init model of this preset (smoke tests, no weights)
    image_size: int | None = None  # default: the checkpoint's (322 for released models)
    recall_ns: tuple[int, ...] = (1, 5, 10, 20)
    rerank_k: int = 100  # 0: global descriptors only
    global_weight: float = 0.0  # re-rank by pair score + this x similarity (detector.py)
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
                reranked = rerank(model, pmap, dense[j], hits, cfg.rerank_k, cfg.global_weight)
                spent.rerank += time.perf_counter() - t0
            yield [kf for kf, _ in hits], reranked


def rerank(
    model: PairVPR,
    pmap: PlaceMap,
    q_dense: np.ndarray,
    hits: list[tuple[int, float]],
    k: int,
    global_weight: float = 0.0,
) -> list[Candidate]:
    """Global hits [(id, similarity)] of one query (dense [N,D] float16) -> its first ``k`` hits
    ordered by re-rank score exactly as the node orders them (`pipeline.map_pair_scores`, then
    `detector.rank_by_pair_score`), followed by the other hits in global order."""
    cands = [
        Candidate(kf, float("nan"), "", float(sim), rank)
        for rank, (kf, sim) in enumerate(hits, start=1)
    ]
    top, rest = cands[:k], cands[k:]
    if not top:
        return cands
    scores = map_pair_scores(model, pmap, q_dense, [c.id for c in top])
    return rank_by_pair_score(top, scores, global_weight) + rest


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
