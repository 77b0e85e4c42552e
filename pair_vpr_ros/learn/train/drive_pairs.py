"""Pairs to tune the pair classifier on, mined from the place maps of drives (issue 24).

Re-ranking in the node faces each keyframe's global top-K among the earlier keyframes the
detector may match: mostly near-duplicate frames of one stretch of road, true revisits among
them. `mine_drive` rebuilds exactly that candidate list for every keyframe of a replayed drive
(`pairvpr-bag-replay ... --pose-topic /ground_truth` saves each keyframe's dense tokens,
descriptor, stamp and pose) and labels the candidates by ground-truth distance: positives within
``gt_radius`` (plus the nearest eligible keyframe within it, which the top-K may miss), hard
negatives beyond ``negative_radius``; those in between are ambiguous and left out.
`rerank_ap` measures a model on the same lists, as the node would rank them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from pair_vpr_ros.errors import DatasetError
from pair_vpr_ros.learn.heldout import average_precision, pair_scores
from pair_vpr_ros.loops.recency import eligible_keyframes
from pair_vpr_ros.loops.records import rerank_score
from pair_vpr_ros.place_map import PlaceMap

RERANK_WEIGHTS = (0, 10, 20, 40)  # global weights w of score = pair + w * global similarity


@dataclass(frozen=True)
class DriveQuery:
    """One keyframe's re-ranking problem: `candidates` [K] ids, best global similarity first,
    with their similarity [K] and ground-truth distance [K] (m); `has_match`: some eligible
    keyframe lies within the gt radius; `positives` / `negatives`: ids to train on."""

    query: int
    candidates: np.ndarray
    similarity: np.ndarray
    distance: np.ndarray
    has_match: bool
    positives: tuple[int, ...]
    negatives: tuple[int, ...]

    @property
    def trainable(self) -> bool:
        return bool(self.positives) and bool(self.negatives)

    @property
    def lonely(self) -> bool:
        """No true match anywhere in the map, but hard negatives: a keyframe of new ground,
        which the node must not call a loop whatever its candidates look like."""
        return not self.has_match and bool(self.negatives)


@dataclass(frozen=True)
class MiningRule:
    """The detector's exclusion and top-K (config/demo.yaml's values) and the label radii."""

    top_k: int = 10
    exclude_recent_s: float = 8.0
    exclude_recent_keyframes: int = 10
    gt_radius: float = 10.0
    negative_radius: float = 15.0


def mine_drive(
    stamps: np.ndarray, positions: np.ndarray, desc: np.ndarray, rule: MiningRule
) -> list[DriveQuery]:
    """stamps [M] s, positions [M,3] (NaN rows: no pose), descriptors [M,C] in keyframe order
    -> the queries that have a pose and at least one eligible candidate, in keyframe order.

    Keyframe q sees the map as the node did (ids < q) under the detector's exclusion
    (`recency.eligible_keyframes`); its candidates are the top-K eligible by dot product."""
    out = []
    for q in range(len(stamps)):
        ok = eligible_keyframes(
            stamps[:q], stamps[q], rule.exclude_recent_s, rule.exclude_recent_keyframes
        )
        if ok is None or np.isnan(positions[q]).any():
            continue
        cand = np.flatnonzero(ok)
        sims = desc[cand] @ desc[q]
        order = np.argsort(-sims, kind="stable")[: rule.top_k]
        dist_all = np.linalg.norm(positions[cand] - positions[q], axis=1)  # NaN: no pose
        top, dist = cand[order], dist_all[order]
        positives = [int(i) for i in top[dist <= rule.gt_radius]]
        within = np.flatnonzero(dist_all <= rule.gt_radius)
        if len(within):
            nearest = int(cand[within[np.argmin(dist_all[within])]])
            positives += [] if nearest in positives else [nearest]
        negatives = tuple(int(i) for i in top[dist > rule.negative_radius])
        out.append(
            DriveQuery(q, top, sims[order], dist, bool(len(within)), tuple(positives), negatives)
        )
    return out


@dataclass
class Drive:
    """A loaded drive: dense tokens [M,N,D] float32 (the map's float16, as the node scores
    them) and its mined queries."""

    path: Path
    dense: Tensor
    queries: list[DriveQuery]

    @property
    def trainable(self) -> list[DriveQuery]:
        return [q for q in self.queries if q.trainable]

    @property
    def lonely(self) -> list[DriveQuery]:
        return [q for q in self.queries if q.lonely]


def load_drive(
    path: Path, rule: MiningRule, dense_shape: tuple[int, int], weights_id: str
) -> Drive:
    """Read and mine one saved place map; DatasetError when it does not fit the model (other
    weights or token shape) or has no poses."""
    with PlaceMap.load(path, read_only=True) as pmap:
        if pmap.fingerprint.split("|")[0].split("+")[0] != weights_id:
            raise DatasetError(
                f"drive map {path} was built with other weights (fingerprint "
                f"{pmap.fingerprint!r}, --init is {weights_id!r}): replay the drive with "
                "pairvpr-bag-replay --weights <the --init checkpoint>"
            )
        if tuple(pmap.dense_shape) != tuple(dense_shape):
            raise DatasetError(
                f"drive map {path} holds dense tokens {tuple(pmap.dense_shape)}, the model "
                f"makes {tuple(dense_shape)}: replay the drive with the --init checkpoint"
            )
        ids = list(range(len(pmap)))
        metas = pmap.all_meta()
        if not any(m.pose is not None for m in metas):
            raise DatasetError(
                f"drive map {path} has no keyframe poses: replay the bag with "
                "--pose-topic /ground_truth (a topic of true poses) so each keyframe gets one"
            )
        stamps = np.array([m.stamp for m in metas], dtype=np.float64)
        nan = (np.nan,) * 3
        positions = np.array([m.pose[:3] if m.pose else nan for m in metas], dtype=np.float64)
        desc = pmap.get_desc(ids).astype(np.float64)
        dense = torch.from_numpy(pmap.get_dense(ids).astype(np.float32))
    return Drive(Path(path), dense, mine_drive(stamps, positions, desc, rule))


def detection_ap(scores: np.ndarray, correct: np.ndarray, with_match: int) -> float:
    """One detection per query (its kept candidate's score [Q], correct [Q]) -> average
    precision over the `with_match` queries that have a true match (0 when none has)."""
    return average_precision(scores, correct, with_match)[0]


@torch.no_grad()
def rerank_ap(
    model: torch.nn.Module, drives: Sequence[Drive], gt_radius: float
) -> dict[str, float | int]:
    """AP of each query's kept candidate: "global" (top-1 by similarity), "pair" (best pair
    score alone) and "rerank_<w>" (best pair + w * similarity) over all drives' queries."""
    was_training = model.training
    model.eval()
    kept: dict[str, tuple[list[float], list[bool]]] = {"global": ([], [])}
    kept.update({f"rerank_{w}": ([], []) for w in RERANK_WEIGHTS})
    for drive in drives:
        for q in drive.queries:
            cands = torch.from_numpy(q.candidates)
            first = torch.full_like(cands, q.query)
            pair = pair_scores(model, drive.dense, first, cands).numpy()
            kept["global"][0].append(float(q.similarity[0]))
            kept["global"][1].append(bool(q.distance[0] <= gt_radius))
            for w in RERANK_WEIGHTS:
                fused = rerank_score(pair, q.similarity, w)
                best = int(np.argmax(fused))
                kept[f"rerank_{w}"][0].append(float(fused[best]))
                kept[f"rerank_{w}"][1].append(bool(q.distance[best] <= gt_radius))
    model.train(was_training)
    with_match = sum(q.has_match for d in drives for q in d.queries)
    out: dict[str, float | int] = {
        name: round(detection_ap(np.array(s), np.array(c, dtype=bool), with_match), 4)
        for name, (s, c) in kept.items()
    }
    out["pair"] = out.pop("rerank_0")
    out["queries"] = sum(len(d.queries) for d in drives)
    out["with_match"] = with_match
    return out
