"""pose_topics: keyframe poses and ground truth chosen apart, each choice said."""

from __future__ import annotations

import pytest

from pair_vpr_ros.errors import BagError
from pair_vpr_ros.offline.bags.pose_topics import PoseTopics, choose_pose_topics

ODOM = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseStamped"
ONE = {"/odom": ODOM}
TWO = {"/odom": ODOM, "/ground_truth": POSE}


def choose(found, pose=None, gt=None) -> PoseTopics:
    return choose_pose_topics(found, pose, gt, "b.mcap")


def test_the_only_pose_topic_is_used_and_said_and_is_the_ground_truth():
    t = choose(ONE)
    assert (t.pose, t.gt, t.warning) == ("/odom", "/odom", None)
    assert t.notes == (
        "keyframe poses: /odom, the bag's only pose topic (choose with --pose-topic, or "
        "--pose-topic none)",
        "ground truth: /odom, the keyframe pose topic (odometry drifts: pass --gt-topic for "
        "true poses)",
    )


def test_several_pose_topics_none_is_used_and_all_are_listed():
    t = choose({"/odom": ODOM, "/mocap": POSE})
    assert (t.pose, t.gt) == (None, None)
    expected = (
        "keyframe poses: none: the bag has 2 pose topics (/mocap, /odom); pick one "
        "with --pose-topic"
    )
    assert t.warning == t.notes[0] == expected
    assert t.notes[1] == "ground truth: none, so no precision / recall (pass --gt-topic)"


@pytest.mark.parametrize("name", ["/ground_truth", "/robot/gt", "/GroundTruth"])
def test_a_topic_named_as_ground_truth_is_the_ground_truth_without_flags(name):
    """Issue 25 #5: /odom beside /ground_truth: the odometry for keyframes, the ground truth
    for the evaluation, and both choices said."""
    t = choose({"/odom": ODOM, name: POSE})
    assert (t.pose, t.gt, t.warning) == ("/odom", name, None)
    assert t.notes == (
        f"keyframe poses: /odom, the bag's only pose topic besides the ground truth {name} "
        "(choose with --pose-topic, or --pose-topic none)",
        f"ground truth: {name}, named as ground truth (choose with --gt-topic, or --gt-topic "
        "none)",
    )
    assert choose({"/odom": ODOM, name: POSE}, gt="none").gt is None
    assert choose({name: POSE}).notes[1].startswith(f"ground truth: {name}, the keyframe pose")
    two = choose({"/odom": ODOM, "/a/gt": POSE, "/b/ground_truth": POSE})
    assert (two.pose, two.gt) == (None, None)  # two named as ground truth: neither is chosen


def test_gt_topic_apart_from_the_odometry_found_beside_it():
    t = choose(TWO, gt="/ground_truth")
    assert (t.pose, t.gt, t.warning) == ("/odom", "/ground_truth", None)
    assert t.notes == (
        "keyframe poses: /odom, the bag's only pose topic besides the ground truth "
        "/ground_truth (choose with --pose-topic, or --pose-topic none)",
        "ground truth: /ground_truth (--gt-topic)",
    )


def test_both_given_and_none():
    t = choose(TWO, pose="/odom", gt="/ground_truth")
    assert (t.pose, t.gt) == ("/odom", "/ground_truth")
    assert t.notes[0] == "keyframe poses: /odom (--pose-topic)"
    t = choose(TWO, pose="none", gt="/ground_truth")
    assert (t.pose, t.gt, t.notes[0]) == (None, "/ground_truth", "keyframe poses: none "
                                          "(--pose-topic none)")  # fmt: skip
    t = choose(ONE, gt="none")
    assert (t.pose, t.gt) == ("/odom", None)
    assert t.notes[1] == "ground truth: none (--gt-topic none): no precision / recall"
    t = choose(ONE, pose="/odom", gt="/odom")  # one topic for both is allowed
    assert (t.pose, t.gt) == ("/odom", "/odom")


def test_no_pose_topic_at_all():
    t = choose({})
    assert (t.pose, t.gt, t.warning) == (None, None, None)
    assert t.notes[0] == (
        "keyframe poses: none (the bag has no Odometry, PoseStamped or "
        "PoseWithCovarianceStamped topic)"
    )
    t = choose(ONE, gt="/odom")  # the only pose topic is the ground truth
    assert (t.pose, t.gt) == (None, "/odom")
    assert t.notes[0].endswith("topic besides the ground truth /odom)")


@pytest.mark.parametrize("flag", ["pose", "gt"])
def test_a_topic_the_bag_lacks_is_an_error_listing_its_pose_topics(flag):
    name = {"pose": "--pose-topic", "gt": "--gt-topic"}[flag]
    with pytest.raises(BagError) as err:
        choose(TWO, **{flag: "/gps"})
    assert str(err.value) == (
        f"{name} /gps is not a pose topic of bag b.mcap (Odometry, PoseStamped or "
        "PoseWithCovarianceStamped); pose topics: /ground_truth "
        "(geometry_msgs/msg/PoseStamped), /odom (nav_msgs/msg/Odometry)"
    )
    with pytest.raises(BagError, match="pose topics: none"):
        choose({}, **{flag: "/gps"})
