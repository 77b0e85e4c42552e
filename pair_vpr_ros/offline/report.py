"""Loop-closure report: loops CSV / JSON, ground-truth precision / recall, PR and trajectory plots.

Ground truth, when keyframes carry poses (positions ``x, y, z`` in metres):

* keyframe ``m`` is a **true match** for query keyframe ``q`` when ``m`` entered the map before
  ``q`` (``m.id < q.id``), ``|q.stamp - m.stamp| >= exclusion_s`` (the detector's recent-frame
  exclusion window ``DetectorConfig.exclude_recent_s``, so the detector could have returned it)
  and the 3-D distance between their positions is ``<= gt_radius`` (default 10 m);
* a loop record is **true** when its match is a true match for its query, **false** otherwise,
  and **unlabelled** when either keyframe has no pose or the match is of another robot or
  session (a prior map: its keyframes are not this run's; unlabelled records are left out);
* **positives** = the number of query keyframes that have at least one true match;
* **precision** = true accepted loops / labelled accepted loops;
  **recall** = query keyframes whose accepted loop is true / positives.

The PR curve sweeps the acceptance threshold over the pair score of every best candidate (one
record per query, accepted or not), so it ignores acceptance checks other than the threshold;
records without a pair score (NaN: re-ranking skipped) are never accepted. The global-only curve
does the same for the top-1 global candidate scored by global similarity.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.loop_messages import LOOP_RECORD_FIELDS, csv_row, record_dict, same_session
from pair_vpr_ros.types import Pose


@dataclass(frozen=True)
class KeyframeInfo:
    """A keyframe as the report needs it: map id, header stamp (s) and pose (or None)."""

    id: int
    stamp: float
    pose: Pose | None


def write_loops_csv(records: Sequence[Any], path: str | Path) -> None:
    """One row per ``LoopRecord`` (accepted or not); the header row is the field names; the
    covariance is one cell of 36 space-separated numbers."""
    with open(path, "w", newline="", encoding="utf-8") as stream:
        writer = csv.writer(stream)
        writer.writerow(LOOP_RECORD_FIELDS)
        for record in records:
            writer.writerow(csv_row(record))


def write_loops_json(records: Sequence[Any], path: str | Path) -> None:
    """A JSON list of records, each an object with every field (``loop_messages.record_dict``)."""
    Path(path).write_text(
        json.dumps([record_dict(r) for r in records], indent=1, allow_nan=False) + "\n",
        encoding="utf-8",
    )


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
        ok = self.precision >= precision
        return float(self.recall[ok].max()) if ok.any() else 0.0

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
    """Ids of the keyframes that have at least one true match among the posed keyframes.

    A sweep along x: keyframes sorted by x are taken `tile` at a time, and only those within
    `gt_radius` in x of a tile are compared with it, `chunk` at a time, so memory stays at a
    few [tile, chunk] tables (about 20 MB) for any number of keyframes, and the work is about
    N x (keyframes in a 2 * gt_radius wide slab) instead of N^2.
    """
    posed = [k for k in keyframes if k.pose is not None]
    if not posed:
        return set()
    xyz = np.array([k.pose[:3] for k in posed], dtype=np.float64)
    order = np.argsort(xyz[:, 0], kind="stable")
    xyz = xyz[order]
    ids = np.array([k.id for k in posed], dtype=np.int64)[order]
    stamps = np.array([k.stamp for k in posed], dtype=np.float64)[order]
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
            hit &= np.abs(stamps[rows, None] - stamps[None, cols]) >= exclusion_s
            found[rows] |= hit.any(axis=1)
    return {int(i) for i in ids[found]}


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

    @property
    def precision(self) -> float | None:
        labelled = self.true_accepted + self.false_accepted
        return self.true_accepted / labelled if labelled else None

    @property
    def recall(self) -> float | None:
        return self.true_accepted / self.positives if self.positives else None

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
    records: Sequence[Any], by_id: dict[int, KeyframeInfo], positives: int, score: str, **gt: float
) -> tuple[PRCurve, list[bool | None]]:
    labels = [
        is_true_loop(by_id.get(r.query_id), by_id.get(r.match_id), **gt)
        if same_session(r)
        else None
        for r in records
    ]
    keep = [i for i, label in enumerate(labels) if label is not None]
    curve = pr_curve(
        [getattr(records[i], score) for i in keep], [labels[i] for i in keep], positives
    )
    return curve, labels


def evaluate_loops(
    records: Sequence[Any],
    keyframes: Sequence[KeyframeInfo],
    gt_radius: float = 10.0,
    exclusion_s: float = 0.0,
    global_records: Sequence[Any] | None = None,
) -> LoopEvaluation:
    """Label ``records`` (one per query) against keyframe poses; PR of re-ranked and global-only.

    ``global_records`` are the top-1 global candidates (one per query), scored by
    ``global_similarity``; the re-ranked curve scores ``records`` by ``pair_score``.
    """
    for name, value in (("gt_radius", gt_radius), ("exclusion_s", exclusion_s)):
        if not (math.isfinite(value) and value >= 0):
            raise ConfigError(f"{name} must be a finite number >= 0, got {value}")
    gt = {"gt_radius": gt_radius, "exclusion_s": exclusion_s}
    by_id = {k.id: k for k in keyframes}
    positives = len(queries_with_true_match(keyframes, **gt))
    reranked, labels = _labelled_curve(records, by_id, positives, "pair_score", **gt)
    global_only = None
    if global_records is not None:
        global_only, _ = _labelled_curve(
            global_records, by_id, positives, "global_similarity", **gt
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
    )


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # files only: never open a window, also on machines with a display
    import matplotlib.pyplot as plt

    return plt


def plot_pr_curves(evaluation: LoopEvaluation, path: str | Path, source: str = "") -> None:
    """PNG of the re-ranked (and global-only) PR curves with the run's operating point;
    ``source`` names the ground truth in the title."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    curves = [("re-ranked (pair score)", evaluation.reranked, "tab:blue")]
    if evaluation.global_only is not None:
        curves.append(("global only (similarity)", evaluation.global_only, "tab:orange"))
    for label, curve, color in curves:
        ap = curve.average_precision()
        ax.step(
            curve.recall, curve.precision, where="post", color=color, label=f"{label}, AP {ap:.3f}"
        )
    if evaluation.precision is not None and evaluation.recall is not None:
        ax.plot(evaluation.recall, evaluation.precision, "k*", ms=11, label="accepted loops")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.02), ylim=(0, 1.05))
    title = f"loop closures, {evaluation.positives} queries with a true match"
    ax.set_title(title + (f"\nground truth: {source}" if source else ""), fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_trajectory(
    positions: np.ndarray,
    keyframes: Sequence[KeyframeInfo],
    records: Sequence[Any],
    labels: Sequence[bool | None],
    path: str | Path,
    source: str = "",
) -> None:
    """PNG of the x/y path ``positions [F, 2+]``, keyframes, and accepted loops (green true,
    red false, grey unlabelled) drawn between their two keyframes (a dot when they coincide);
    ``source`` names the ground truth the positions come from in the title."""
    plt = _pyplot()
    from matplotlib.collections import LineCollection

    by_id = {k.id: k.pose for k in keyframes if k.pose is not None}
    fig, ax = plt.subplots(figsize=(6, 6))
    if len(positions):
        ax.plot(positions[:, 0], positions[:, 1], "-", color="0.6", lw=1, label="path")
    if by_id:
        xy = np.array([pose[:2] for pose in by_id.values()])
        ax.plot(xy[:, 0], xy[:, 1], ".", color="tab:blue", ms=4, label="keyframes")
    colors = {True: "tab:green", False: "tab:red", None: "0.4"}
    names = {True: "true loop", False: "false loop", None: "loop (no pose)"}
    segments: dict[bool | None, list] = {True: [], False: [], None: []}
    for record, label in zip(records, labels, strict=True):
        q, m = by_id.get(record.query_id), by_id.get(record.match_id)
        if record.accepted and q is not None and m is not None and same_session(record):
            segments[label].append(((q[0], q[1]), (m[0], m[1])))
    for label, lines in segments.items():  # one artist per kind: thousands of loops stay cheap
        if lines:
            ends = np.asarray(lines, dtype=np.float64).reshape(-1, 2)
            ax.add_collection(LineCollection(lines, colors=colors[label], linewidths=1.5))
            ax.plot(ends[:, 0], ends[:, 1], "o", color=colors[label], ms=4, label=names[label])
    ax.set(xlabel="x [m]", ylabel="y [m]", aspect="equal")
    if source:
        ax.set_title(f"path and loops, ground truth: {source}", fontsize=10)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_report(
    out_dir: str | Path,
    records: Sequence[Any],
    keyframes: Sequence[KeyframeInfo],
    positions: np.ndarray | None = None,
    gt_radius: float = 10.0,
    exclusion_s: float = 0.0,
    global_records: Sequence[Any] | None = None,
    source: str = "",
) -> LoopEvaluation | None:
    """Write ``loops.csv`` and ``loops.json``; with keyframe poses also evaluate and write
    ``pr_curve.png`` and ``trajectory.png`` (``positions [F, 3]``: every posed frame, in order;
    ``source``: where the poses come from, named in the plots' titles).
    Returns the evaluation, or None without poses."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_loops_csv(records, out / "loops.csv")
    write_loops_json(records, out / "loops.json")
    if not any(k.pose is not None for k in keyframes):
        return None
    evaluation = evaluate_loops(records, keyframes, gt_radius, exclusion_s, global_records)
    plot_pr_curves(evaluation, out / "pr_curve.png", source)
    if positions is None:
        positions = np.array([k.pose[:3] for k in keyframes if k.pose is not None])
    plot_trajectory(
        positions, keyframes, records, evaluation.labels, out / "trajectory.png", source
    )
    return evaluation
