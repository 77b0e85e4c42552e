"""Loops into prior maps against ground truth, reported apart from the run's own (live) loops.

A prior map's keyframes are not this run's, so ``loop_truth`` leaves their loops unlabelled.
They are labelled here where the bag's ground truth covers them: a prior keyframe recorded from
this same bag (its ``source`` names the bag) whose stamp the ground truth has, and whose stored
pose (the pose topic the map was built with) is the bag's pose-topic pose at that stamp, when
both exist -- the prior map was built from this very recording. Its true position is then the
ground truth at its stamp. Other prior keyframes (another drive, another clock) stay
unlabelled: their stored poses are in their own drive's odometry frame.

* a loop into a prior map is **true** when both keyframes' positions lie within ``gt_radius``
  (no recency window: a prior map is never "recent"), **false** when farther, **unlabelled**
  when either position is unknown;
* **positives**: live keyframes with a labelled prior keyframe within ``gt_radius``;
* **precision** = true / labelled accepted loops; **recall** = live keyframes whose accepted
  prior-map loop is true / positives.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from pair_vpr_ros.messages.loop import same_session
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo, KeyframeLookup, share
from pair_vpr_ros.types import Pose, PoseTrack

PriorKey = tuple[str, str, int]  # robot, session, keyframe id
SAME_POSE_M = 0.01  # a stored pose this close to the bag's pose topic: the same recording


@dataclass(frozen=True)
class PriorEvaluation:
    """Accepted loops into prior maps by label; ``covered``: prior keyframes with a position."""

    gt_radius: float
    covered: int
    prior_keyframes: int
    positives: int
    accepted: int
    true_accepted: int
    false_accepted: int
    unlabelled_accepted: int
    true_queries: int  # live keyframes with a true accepted prior-map loop (one per map at most)

    @property
    def precision(self) -> float | None:
        return share(self.true_accepted, self.true_accepted + self.false_accepted)

    @property
    def recall(self) -> float | None:
        return share(self.true_queries, self.positives)

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "precision": self.precision, "recall": self.recall}


def prior_positions(
    metas: Iterable[Any],
    bag_name: str,
    truth: PoseTrack | None,
    poses: PoseTrack | None,
    tolerance: float,
) -> dict[PriorKey, Pose]:
    """Ground-truth poses of the prior maps' keyframes (``KeyframeMeta``) this bag recorded."""
    out: dict[PriorKey, Pose] = {}
    if truth is None:
        return out
    for meta in metas:
        if meta.source.rsplit("#", 1)[0] != bag_name:
            continue
        true_pose = truth.nearest(meta.stamp, tolerance)
        recorded = poses.nearest(meta.stamp, tolerance) if poses is not None else None
        if true_pose is None:
            continue
        if meta.pose is not None and recorded is not None:
            gap = np.linalg.norm(np.subtract(meta.pose[:3], recorded[:3]))
            if gap > SAME_POSE_M:
                continue  # the same name, another recording
        out[(meta.robot, meta.session, meta.id)] = tuple(true_pose)
    return out


def _near(a: Pose | None, b: Pose | None, radius: float) -> bool | None:
    if a is None or b is None:
        return None
    return bool(np.linalg.norm(np.subtract(a[:3], b[:3])) <= radius)


def evaluate_prior_loops(
    records: Sequence[Any],
    live: Sequence[KeyframeInfo],
    prior: dict[PriorKey, Pose],
    prior_keyframes: int,
    gt_radius: float = 10.0,
) -> PriorEvaluation:
    """Label the accepted loops of ``records`` whose match is another robot or session."""
    lookup = KeyframeLookup(live)  # a query the map did not store: by its stamp
    into_prior = [r for r in records if r.accepted and not same_session(r)]
    labels = [
        _near(getattr(lookup.query(r), "pose", None),
              prior.get((r.match_robot, r.match_session, r.match_id)), gt_radius)
        for r in into_prior
    ]  # fmt: skip
    true_queries = {r.query_stamp for r, label in zip(into_prior, labels, strict=True) if label}
    positives = 0
    if prior:
        xyz = np.array([p[:3] for p in prior.values()], dtype=np.float64)
        for pose in (k.pose for k in live):
            if pose is not None:
                gaps = np.linalg.norm(xyz - np.asarray(pose[:3]), axis=1)
                positives += bool((gaps <= gt_radius).any())
    return PriorEvaluation(
        gt_radius=gt_radius,
        covered=len(prior),
        prior_keyframes=prior_keyframes,
        positives=positives,
        accepted=len(labels),
        true_accepted=sum(label is True for label in labels),
        false_accepted=sum(label is False for label in labels),
        unlabelled_accepted=sum(label is None for label in labels),
        true_queries=len(true_queries),
    )
