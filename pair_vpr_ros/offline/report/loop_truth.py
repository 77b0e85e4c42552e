"""Loop closures against ground truth: true / false / unlabelled loops, precision, recall, PR.

Ground truth, when keyframes carry poses (positions ``x, y, z`` in metres):

* keyframe ``m`` is a **true match** for query keyframe ``q`` when ``m`` entered the map before
  ``q`` (``m.id < q.id``), ``|q.stamp - m.stamp| >= exclusion_s`` (the detector's recent-frame
  exclusion window ``DetectorConfig.exclude_recent_s``, so the detector could have returned it)
  and the 3-D distance between their positions is ``<= gt_radius`` (default 10 m);
* a loop record is **true** when its match is a true match for its query, **false** otherwise,
  and **unlabelled** when either keyframe has no pose or the match is of another robot or
  session (a prior map: its keyframes are not this run's; unlabelled records are left out);
* a query the map did not store (`map_growth` places: a stored keyframe represents it, its
  records carry ``query_id`` -1) is a query all the same: its ``KeyframeInfo`` has
  ``stored=False`` and as ``id`` the number of keyframes stored before it, so exactly those
  can be its true matches; its records are found by their ``query_stamp``. It is never a match;
* **positives** = the number of query keyframes (stored or not) with at least one true match;
* **precision** = true accepted loops / labelled accepted loops;
  **recall** = query keyframes whose accepted loop is true / positives.

The PR curve sweeps the acceptance threshold over the pair score of every best candidate (one
record per query, accepted or not), so it ignores acceptance checks other than the threshold;
records without a pair score (NaN: re-ranking skipped) are never accepted. The global-only curve
does the same for the top-1 global candidate scored by global similarity.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.loops.records import rerank_score
from pair_vpr_ros.messages.loop import same_session
from pair_vpr_ros.types import Pose


@dataclass(frozen=True)
class KeyframeInfo:
    """A keyframe as the report needs it: map id, header stamp (s) and pose (or None).
    stored False: a query the map did not store (map_growth), ``id`` = keyframes stored before
    it (module docstring)."""

    id: int
    stamp: float
    pose: Pose | None
    stored: bool = True


class KeyframeLookup:
    """A record's query and match among the run's keyframes: a stored query by its
    ``query_id``, one the map did not store (``query_id`` -1) by its ``query_stamp``."""

    def __init__(self, keyframes: Sequence[KeyframeInfo]) -> None:
        self.by_id = {k.id: k for k in keyframes if k.stored}
        self.by_stamp = {k.stamp: k for k in keyframes if not k.stored}

    def query(self, record: Any) -> KeyframeInfo | None:
        if record.query_id >= 0:
            return self.by_id.get(record.query_id)
        return self.by_stamp.get(record.query_stamp)

    def match(self, record: Any) -> KeyframeInfo | None:
        return self.by_id.get(record.match_id)


@dataclass(frozen=True)
class PRCurve:
    """Precision / recall at each threshold, thresholds descending: each ``[T]`` float64."""

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray

    def average_precision(self) -> float:
        """Area under the step PR curve: sum over thresholds of recall gain x precision."""
        gains = np.diff(np.concatenate([[0.0], self.recall]))
        return float(np.sum(gains * self.precision))

    def recall_at_full_precision(self) -> float:
        """The highest recall reached with no false loop accepted (0 when none)."""
        return self.recall_at_precision(1.0)

    def recall_at_precision(self, precision: float) -> float:
        """The highest recall reached at a threshold whose precision is >= ``precision``."""
        point = self.operating_point(precision)
        return point[2] if point is not None else 0.0

    def operating_point(self, precision: float) -> tuple[float, float, float] | None:
        """(threshold, precision, recall) of the highest recall at precision >= ``precision``
        (the first such threshold on a tie); None when no threshold reaches it."""
        ok = np.flatnonzero(self.precision >= precision)
        if not len(ok):
            return None
        best = ok[np.argmax(self.recall[ok])]
        return float(self.thresholds[best]), float(self.precision[best]), float(self.recall[best])

    def at_threshold(self, threshold: float) -> tuple[float, float] | None:
        """(precision, recall) when every score >= ``threshold`` is accepted; None when no
        threshold of the curve is that high."""
        at = np.flatnonzero(self.thresholds >= threshold)
        if not len(at):
            return None
        return float(self.precision[at[-1]]), float(self.recall[at[-1]])

    def best_f1(self) -> tuple[float, float | None]:
        """``(F1, threshold)`` of the best F1 point; ``(0.0, None)`` for an empty curve."""
        denom = self.precision + self.recall
        f1 = np.divide(
            2 * self.precision * self.recall, denom, out=np.zeros_like(denom), where=denom > 0
        )
        if len(f1) == 0:
            return 0.0, None
        best = int(np.argmax(f1))
        return float(f1[best]), float(self.thresholds[best])

    def to_dict(self) -> dict[str, Any]:
        f1, threshold = self.best_f1()
        return {
            "average_precision": self.average_precision(),
            "recall_at_100_precision": self.recall_at_full_precision(),
            "recall_at_90_precision": self.recall_at_precision(0.9),
            "best_f1": f1,
            "best_f1_threshold": threshold,
        }


def pr_curve(scores: Sequence[float], labels: Sequence[bool], positives: int) -> PRCurve:
    """PR curve of accepting every record with ``score >= threshold``; ``positives`` = recall's
    denominator. ``scores [R]``, ``labels [R]`` (True = true loop)."""
    scores = np.asarray(scores, dtype=np.float64)
    hits = np.asarray(labels, dtype=bool)
    scored = ~np.isnan(scores)  # NaN: no score, never above any threshold
    scores, hits = scores[scored], hits[scored]
    order = np.argsort(-scores, kind="stable")
    scores, hits = scores[order], hits[order]
    # one point per distinct score: the last record of each run of equal scores
    last = (
        np.flatnonzero(np.append(np.diff(scores) != 0, True)) if len(scores) else np.zeros(0, int)
    )
    tp = np.cumsum(hits)[last].astype(np.float64)
    accepted = (last + 1).astype(np.float64)
    recall = tp / positives if positives > 0 else np.zeros_like(tp)
    return PRCurve(scores[last], tp / accepted, recall)


def is_true_loop(
    query: KeyframeInfo | None, match: KeyframeInfo | None, gt_radius: float, exclusion_s: float
) -> bool | None:
    """Whether ``match`` is a true match for ``query`` (module docstring); None without poses."""
    if query is None or match is None or query.pose is None or match.pose is None:
        return None
    if not match.stored:  # never a match: the map has no such keyframe
        return False
    distance = float(np.linalg.norm(np.subtract(query.pose[:3], match.pose[:3])))
    return (
        match.id < query.id
        and abs(query.stamp - match.stamp) >= exclusion_s
        and distance <= gt_radius
    )


def queries_with_true_match(
    keyframes: Sequence[KeyframeInfo],
    gt_radius: float,
    exclusion_s: float,
    tile: int = 256,
    chunk: int = 2048,
) -> set[int]:
    """Ids of the stored keyframes that have at least one true match (`true_match_mask`)."""
    hit = true_match_mask(keyframes, gt_radius, exclusion_s, tile, chunk)
    return {k.id for k, h in zip(keyframes, hit, strict=True) if h and k.stored}


def true_match_mask(
    keyframes: Sequence[KeyframeInfo],
    gt_radius: float,
    exclusion_s: float,
    tile: int = 256,
    chunk: int = 2048,
) -> np.ndarray:
    """[K] bool: which of ``keyframes`` have at least one true match among the posed stored
    keyframes (one the map did not store is a query, never a match).

    A sweep along x: keyframes sorted by x are taken `tile` at a time, and only those within
    `gt_radius` in x of a tile are compared with it, `chunk` at a time, so memory stays at a
    few [tile, chunk] tables (about 20 MB) for any number of keyframes, and the work is about
    N x (keyframes in a 2 * gt_radius wide slab) instead of N^2.
    """
    where = np.array([k.pose is not None for k in keyframes], dtype=bool)
    posed = [k for k in keyframes if k.pose is not None]
    if not posed:
        return where
    xyz = np.array([k.pose[:3] for k in posed], dtype=np.float64)
    order = np.argsort(xyz[:, 0], kind="stable")
    xyz = xyz[order]
    ids = np.array([k.id for k in posed], dtype=np.int64)[order]
    stamps = np.array([k.stamp for k in posed], dtype=np.float64)[order]
    stored = np.array([k.stored for k in posed], dtype=bool)[order]
    found = np.zeros(len(posed), dtype=bool)
    for start in range(0, len(posed), tile):
        rows = slice(start, min(start + tile, len(posed)))
        lo = int(np.searchsorted(xyz[:, 0], xyz[rows.start, 0] - gt_radius, side="left"))
        hi = int(np.searchsorted(xyz[:, 0], xyz[rows.stop - 1, 0] + gt_radius, side="right"))
        for first in range(lo, hi, chunk):
            cols = slice(first, min(first + chunk, hi))
            squared = np.zeros((rows.stop - rows.start, cols.stop - cols.start))
            for axis in range(3):
                squared += np.square(xyz[rows, axis, None] - xyz[None, cols, axis])
            hit = np.sqrt(squared) <= gt_radius
            hit &= ids[None, cols] < ids[rows, None]
            hit &= stored[None, cols]
            hit &= np.abs(stamps[rows, None] - stamps[None, cols]) >= exclusion_s
            found[rows] |= hit.any(axis=1)
    hit = np.zeros(len(posed), dtype=bool)
    hit[order] = found  # back from x order to the order of `posed`
    out = np.zeros(len(keyframes), dtype=bool)
    out[where] = hit
    return out


def share(part: int, whole: int) -> float | None:
    """part / whole, None when there is nothing to divide (no labelled loop, no positive)."""
    return part / whole if whole else None


@dataclass(frozen=True)
class LoopEvaluation:
    """Ground-truth evaluation of one run; ``labels[i]`` belongs to ``records[i]``."""

    gt_radius: float
    exclusion_s: float
    positives: int
    labels: list[bool | None]
    accepted: int
    true_accepted: int
    false_accepted: int
    unlabelled_accepted: int
    reranked: PRCurve
    global_only: PRCurve | None
    # [len(keyframes)] bool, in the order evaluated: which keyframes have a true match
    revisits: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def precision(self) -> float | None:
        return share(self.true_accepted, self.true_accepted + self.false_accepted)

    @property
    def recall(self) -> float | None:
        return share(self.true_accepted, self.positives)

    def to_dict(self) -> dict[str, Any]:
        return {
            "gt_radius_m": self.gt_radius,
            "exclusion_s": self.exclusion_s,
            "positives": self.positives,
            "accepted": self.accepted,
            "true_accepted": self.true_accepted,
            "false_accepted": self.false_accepted,
            "unlabelled_accepted": self.unlabelled_accepted,
            "precision": self.precision,
            "recall": self.recall,
            "reranked": self.reranked.to_dict(),
            "global_only": self.global_only.to_dict() if self.global_only else None,
        }


def _labelled_curve(
    records: Sequence[Any],
    lookup: KeyframeLookup,
    positives: int,
    score: Callable[[Any], float],
    **gt: float,
) -> tuple[PRCurve, list[bool | None]]:
    labels = [
        is_true_loop(lookup.query(r), lookup.match(r), **gt) if same_session(r) else None
        for r in records
    ]
    keep = [i for i, label in enumerate(labels) if label is not None]
    curve = pr_curve([score(records[i]) for i in keep], [labels[i] for i in keep], positives)
    return curve, labels


def evaluate_loops(
    records: Sequence[Any],
    keyframes: Sequence[KeyframeInfo],
    gt_radius: float = 10.0,
    exclusion_s: float = 0.0,
    global_records: Sequence[Any] | None = None,
    global_weight: float = 0.0,
) -> LoopEvaluation:
    """Label ``records`` (one per query) against keyframe poses; PR of re-ranked and global-only.

    ``global_records`` are the top-1 global candidates (one per query), scored by
    ``global_similarity``; the re-ranked curve scores ``records`` by the detector's re-rank
    score, ``pair_score + global_weight x global_similarity`` (`detector.rerank_score`).
    """
    for name, value in (("gt_radius", gt_radius), ("exclusion_s", exclusion_s)):
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"{name} must be a finite number >= 0, got {value}")
    gt = {"gt_radius": gt_radius, "exclusion_s": exclusion_s}
    lookup = KeyframeLookup(keyframes)
    revisits = true_match_mask(keyframes, **gt)
    positives = int(revisits.sum())

    def reranked_score(r: Any) -> float:
        return rerank_score(r.pair_score, r.global_similarity, global_weight)

    reranked, labels = _labelled_curve(records, lookup, positives, reranked_score, **gt)
    global_only = None
    if global_records is not None:
        global_only, _ = _labelled_curve(
            global_records, lookup, positives, lambda r: r.global_similarity, **gt
        )
    accepted = [label for r, label in zip(records, labels, strict=True) if r.accepted]
    return LoopEvaluation(
        gt_radius=gt_radius,
        exclusion_s=exclusion_s,
        positives=positives,
        labels=labels,
        accepted=len(accepted),
        true_accepted=sum(label is True for label in accepted),
        false_accepted=sum(label is False for label in accepted),
        unlabelled_accepted=sum(label is None for label in accepted),
        reranked=reranked,
        global_only=global_only,
        revisits=revisits,
    )
