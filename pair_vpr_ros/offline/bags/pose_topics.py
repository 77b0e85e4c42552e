"""Which pose topics a replay uses: odometry attached to keyframes, ground truth for evaluation.

On a robot they differ: odometry drifts, ground truth (motion capture, RTK GPS, a survey-grade
SLAM result) does not, and a loop closure judged against drifted odometry is judged wrongly. So
the keyframe poses (``--pose-topic``: saved in the map, as the node's ``pose_topic`` does) and
the evaluation's ground truth (``--gt-topic``) are chosen apart, and every choice is said:

* ``--pose-topic`` not given: the bag's only pose topic (besides ``--gt-topic``) is used; with
  several, none is, and the message lists them.
* ``--gt-topic`` not given: the bag's one pose topic named as ground truth (``ground_truth``,
  ``groundtruth`` or ``gt`` as its last part, e.g. ``/ground_truth``, ``/robot/gt``) is the
  ground truth, and the keyframe poses come from the others as if it had been given; without
  one, the keyframe pose topic is the ground truth (the message says that it may drift).
* ``none`` for either: not used.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from pair_vpr_ros.errors import BagError

NONE = "none"
GT_NAMES = ("ground_truth", "groundtruth", "gt")  # last part of a topic named as ground truth
KINDS = "Odometry, PoseStamped or PoseWithCovarianceStamped"


@dataclass(frozen=True)
class PoseTopics:
    """The chosen topics (None: not used) and one line per choice saying how it was made."""

    pose: str | None  # attached to keyframes
    gt: str | None  # ground truth of the evaluation
    notes: tuple[str, str]  # (keyframe poses, ground truth), printed and in summary.json
    warning: str | None = None  # several candidates, none chosen


def _checked(topic: str, found: Mapping[str, str], bag: str, flag: str) -> str:
    if topic not in found:
        listed = ", ".join(f"{t} ({found[t]})" for t in sorted(found)) or "none"
        raise BagError(
            f"{flag} {topic} is not a pose topic of bag {bag} ({KINDS}); pose topics: {listed}"
        )
    return topic


def choose_pose_topics(
    found: Mapping[str, str], pose: str | None, gt: str | None, bag: str
) -> PoseTopics:
    """Apply the rules above to the bag's pose topics ``found`` ({topic: type}, bag order) and
    the ``--pose-topic`` / ``--gt-topic`` values (None: not given). BagError for a given topic
    the bag does not hold as a pose topic."""
    warning = None
    by_name = None
    if gt is None:
        named = [t for t in found if t.rstrip("/").rsplit("/", 1)[-1].lower() in GT_NAMES]
        by_name = named[0] if len(named) == 1 and len(found) > 1 else None
        gt = by_name
    gt_given = gt not in (None, NONE)
    if gt_given:
        gt = _checked(gt, found, bag, "--gt-topic")
    if pose == NONE:
        pose, pose_note = None, "keyframe poses: none (--pose-topic none)"
    elif pose is not None:
        pose = _checked(pose, found, bag, "--pose-topic")
        pose_note = f"keyframe poses: {pose} (--pose-topic)"
    else:
        others = sorted(t for t in found if not (gt_given and t == gt))
        besides = f" besides the ground truth {gt}" if gt_given else ""
        if len(others) == 1:
            pose = others[0]
            pose_note = (
                f"keyframe poses: {pose}, the bag's only pose topic{besides} (choose with "
                "--pose-topic, or --pose-topic none)"
            )
        elif others:
            pose_note = (
                f"keyframe poses: none: the bag has {len(others)} pose topics{besides} "
                f"({', '.join(others)}); pick one with --pose-topic"
            )
            warning = pose_note
        else:
            pose_note = f"keyframe poses: none (the bag has no {KINDS} topic{besides})"
    if by_name is not None:
        gt_note = (
            f"ground truth: {gt}, named as ground truth (choose with --gt-topic, or --gt-topic "
            "none)"
        )
    elif gt_given:
        gt_note = f"ground truth: {gt} (--gt-topic)"
    elif gt == NONE:
        gt, gt_note = None, "ground truth: none (--gt-topic none): no precision / recall"
    elif pose is not None:
        gt = pose
        gt_note = (
            f"ground truth: {pose}, the keyframe pose topic (odometry drifts: pass --gt-topic "
            "for true poses)"
        )
    else:
        gt_note = "ground truth: none, so no precision / recall (pass --gt-topic)"
    return PoseTopics(pose, gt, (pose_note, gt_note), warning)
