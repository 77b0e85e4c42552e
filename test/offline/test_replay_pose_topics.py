"""Replay with odometry and ground truth kept apart: which topic is attached to keyframes, which
one the evaluation uses, and how each choice is said (stdout, summary.json, plot titles).

bag_fixtures.revisit_world (revisits of places 0-4 at t >= 100 s, then two new places): the
ground truth puts every revisit where the place was; the odometry has drifted 25 m sideways by
then, so judged against it no revisit is a true loop.
"""

from __future__ import annotations

import json

import pytest
from bag_fixtures import ODOMETRY, POSE_STAMPED, TS2, pose_msg, revisit_world, write_rosbag2

from pair_vpr_ros.errors import BagError
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.model import save_pairvpr
from pair_vpr_ros.offline.replay.cli import main
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag
from pair_vpr_ros.place_map import PlaceMap

CONFIG = DetectorConfig(
    top_k=1, score_threshold=-1e9, keyframe_max_similarity=1.0,
    exclude_recent_s=30.0, exclude_recent_keyframes=0,
)  # fmt: skip
DRIFT = 25.0  # metres of sideways odometry drift by the revisits


def _drifted(truth):
    return [(t, (x, y + (DRIFT if t >= 100 else 0.0), z)) for t, (x, y, z) in truth]


def write_bag(path, with_truth=True, truth_topic="/ground_truth"):
    """/odom (drifting Odometry) and, ``with_truth``, ``truth_topic`` (PoseStamped)."""
    images, truth = revisit_world()
    extra = [
        (truth_topic, POSE_STAMPED, pose_msg(TS2, POSE_STAMPED, t, xyz), t) for t, xyz in truth
    ]
    return write_rosbag2(
        path, images, _drifted(truth), pose_topic="/odom", pose_type=ODOMETRY,
        extra=extra if with_truth else [],
    )  # fmt: skip


def replay(tmp_path, bag, model, **kw):
    options = ReplayOptions(progress=False, **kw)
    return replay_bag(bag, tmp_path / "out", options, model=model, config=CONFIG)


def test_gt_topic_judges_loops_while_keyframes_keep_the_odometry(tmp_path, tiny_model):
    bag = write_bag(tmp_path / "bag")
    s = replay(tmp_path, bag, tiny_model, gt_topic="/ground_truth")
    assert (s.pose_topic, s.gt_topic, s.warnings) == ("/odom", "/ground_truth", [])
    assert s.notes == [
        "keyframe poses: /odom, the bag's only pose topic besides the ground truth "
        "/ground_truth (choose with --pose-topic, or --pose-topic none)",
        "ground truth: /ground_truth (--gt-topic)",
    ]
    ev = s.evaluation
    assert (ev["gt_topic"], ev["true_accepted"], ev["false_accepted"]) == ("/ground_truth", 5, 2)
    assert (ev["precision"], ev["recall"]) == (5 / 7, 1.0)
    with PlaceMap.load(tmp_path / "out" / "map") as saved:  # the map keeps the odometry
        assert saved.meta(10).pose[:3] == (0.0, DRIFT, 0.0)
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert (saved["pose_topic"], saved["gt_topic"]) == ("/odom", "/ground_truth")
    assert saved["evaluation"]["gt_topic"] == "/ground_truth"


def test_judged_against_the_drifting_odometry_the_same_loops_are_false(tmp_path, tiny_model):
    bag = write_bag(tmp_path / "bag")
    s = replay(tmp_path, bag, tiny_model, pose_topic="/odom", gt_topic="/odom")
    ev = s.evaluation
    assert (ev["gt_topic"], ev["true_accepted"], ev["false_accepted"]) == ("/odom", 0, 7)
    assert s.notes == ["keyframe poses: /odom (--pose-topic)", "ground truth: /odom (--gt-topic)"]


def test_the_only_pose_topic_is_found_said_and_used_for_both(tmp_path, tiny_model):
    s = replay(tmp_path, write_bag(tmp_path / "bag", with_truth=False), tiny_model)
    assert (s.pose_topic, s.gt_topic, s.evaluation["gt_topic"]) == ("/odom", "/odom", "/odom")
    assert s.notes[0].startswith("keyframe poses: /odom, the bag's only pose topic (")
    assert s.notes[1].startswith("ground truth: /odom, the keyframe pose topic (odometry drifts")


def test_several_pose_topics_none_is_used_and_they_are_listed(tmp_path, tiny_model):
    s = replay(tmp_path, write_bag(tmp_path / "bag", truth_topic="/mocap/pose"), tiny_model)
    listed = (
        "keyframe poses: none: the bag has 2 pose topics (/mocap/pose, /odom); pick one with "
        "--pose-topic"
    )
    assert (s.pose_topic, s.gt_topic, s.evaluation) == (None, None, None)
    assert s.warnings == [listed] and s.notes[0] == listed
    with PlaceMap.load(tmp_path / "out" / "map") as saved:
        assert saved.meta(0).pose is None
    assert not (tmp_path / "out" / "pr_curve.png").exists()


def test_gt_topic_none_and_pose_topic_none(tmp_path, tiny_model):
    bag = write_bag(tmp_path / "bag", with_truth=False)
    s = replay(tmp_path, bag, tiny_model, gt_topic="none")
    assert (s.pose_topic, s.gt_topic, s.evaluation) == ("/odom", None, None)
    s = replay(tmp_path, bag, tiny_model, pose_topic="none", gt_topic="/odom", overwrite=True)
    assert (s.pose_topic, s.gt_topic, s.evaluation["true_accepted"]) == (None, "/odom", 0)
    with PlaceMap.load(tmp_path / "out" / "map") as saved:
        assert saved.meta(0).pose is None


def test_a_gt_topic_the_bag_lacks_is_an_error(tmp_path, tiny_model):
    with pytest.raises(BagError, match=r"^--gt-topic /gps is not a pose topic of bag bag "):
        replay(tmp_path, write_bag(tmp_path / "bag"), tiny_model, gt_topic="/gps")


@pytest.fixture(scope="module")
def weights(tmp_path_factory, tiny_model):
    return save_pairvpr(tiny_model, tmp_path_factory.mktemp("w") / "tiny.pth")


def test_cli_prints_each_choice_and_the_ground_truth_of_its_figures(tmp_path, weights, capsys):
    bag, out = write_bag(tmp_path / "bag"), tmp_path / "out"
    argv = [str(bag), "--weights", str(weights), "--out", str(out), "--quiet", "--top-k", "1"]
    assert main([*argv, "--gt-topic", "/ground_truth"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[:2] == [
        "keyframe poses: /odom, the bag's only pose topic besides the ground truth "
        "/ground_truth (choose with --pose-topic, or --pose-topic none)",
        "ground truth: /ground_truth (--gt-topic)",
    ]
    assert printed[2].startswith("precision ")
    assert printed[2].endswith("; ground truth /ground_truth)")
    assert json.loads((out / "summary.json").read_text())["notes"] == printed[:2]
    # Issue 25: no flags, /ground_truth beside /odom: each is used as its name says, and the
    # choice is said in the run's first lines (before the model loads), without a warning
    assert main([*argv, "--overwrite"]) == 0
    printed, err = capsys.readouterr()
    assert printed.splitlines()[:2] == [
        "keyframe poses: /odom, the bag's only pose topic besides the ground truth "
        "/ground_truth (choose with --pose-topic, or --pose-topic none)",
        "ground truth: /ground_truth, named as ground truth (choose with --gt-topic, or "
        "--gt-topic none)",
    ]
    assert err == ""
    assert main([*argv, "--overwrite", "--gt-topic", "/gps"]) == 1
    assert capsys.readouterr().err == (
        "error: --gt-topic /gps is not a pose topic of bag bag (Odometry, PoseStamped or "
        "PoseWithCovarianceStamped); pose topics: /ground_truth "
        "(geometry_msgs/msg/PoseStamped), /odom (nav_msgs/msg/Odometry)\n"
    )
