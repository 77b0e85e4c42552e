"""OUT/suggested_params.yaml: a threshold chosen by deciding the bag's keyframes again through
the detector's own code, which the same bag, replayed with that file, holds to.

The revisit world (test/bag_fixtures.py) with the tiny network, top_k 1 and sequence_margin 1.0:
keyframes 10-14 revisit places 0-4 (true, pair scores -0.13, 0.15, 0.61, -1.57, -0.57), keyframes
15 and 16 are new places whose best candidates are keyframe 3 (false, -1.49 and -1.76). A raw PR
curve puts precision 1.0 at any threshold in (-1.49, -0.57], with 4 true loops. The detector
does not: at -0.6 keyframe 13 follows keyframe 12's loop (2 -> 3) at -1.6, and so does keyframe
15 (false) keyframe 14's (4 -> 3): 5 true, 1 false. Keeping keyframe 15 out takes a threshold
above -0.49, where keyframe 13 is no follower and so keyframe 14 (-0.57) is none either: 3 true.
"""

from __future__ import annotations

import pytest
import yaml
from bag_fixtures import revisit_world, write_rosbag2

from pair_vpr_ros.model import save_pairvpr
from pair_vpr_ros.offline.replay.cli import main
from pair_vpr_ros.params.file import read_params_file

SETTINGS = """/**:
  ros__parameters:
    top_k: 1
    score_threshold: -1000.0
    sequence_margin: 1.0
    keyframe_max_similarity: 1.0
    exclude_recent_s: 30.0
    exclude_recent_keyframes: 0
    min_frame_interval: 0.0
    relative_pose: false
"""


@pytest.fixture(scope="module")
def weights(tmp_path_factory, tiny_model):
    return save_pairvpr(tiny_model, tmp_path_factory.mktemp("w") / "tiny.pth")


def replay(bag, out, params, weights, *flags) -> dict:
    argv = [str(bag), "--weights", str(weights), "--params-file", str(params), "--out", str(out)]
    assert main([*argv, "--quiet", "--no-report", "--gt-topic", "/ground_truth", *flags]) == 0
    return yaml.safe_load((out / "summary.json").read_text())


def test_suggested_threshold_holds_when_the_bag_is_replayed_with_it(tmp_path, weights, capsys):
    images, poses = revisit_world()
    bag = write_rosbag2(tmp_path / "bag", images, poses, pose_topic="/ground_truth")
    (tmp_path / "start.yaml").write_text(SETTINGS)
    first = replay(bag, tmp_path / "a", tmp_path / "start.yaml", weights)
    ev = first["evaluation"]
    assert (ev["true_accepted"], ev["false_accepted"]) == (5, 2)
    s = first["suggestion"]
    assert (s["target_precision"], s["reached"], s["mismatches_with_run"]) == (0.99, True, 0)
    assert -0.49 < s["score_threshold"] <= -0.13 and s["global_floor"] == -1.0
    expected = s["expected"]
    assert (expected["accepted"], expected["true"], expected["false"]) == (3, 3, 0)
    assert expected["recall"] == 0.6 and s["warnings"] == []
    printed = capsys.readouterr().out
    assert f"suggested score_threshold {s['score_threshold']:g} (global_floor -1) reaches " \
        "precision 0.99 on this bag: expected precision 1.000, recall 0.600 (3 loops, 0 " \
        "false)" in printed  # fmt: skip

    # a node parameter file: the run's settings, the suggested threshold, the figures in words
    suggested = tmp_path / "a" / "suggested_params.yaml"
    values = read_params_file(suggested)
    assert values["score_threshold"] == s["score_threshold"]
    assert (values["top_k"], values["sequence_margin"], values["relative_pose"]) == (1, 1.0, False)
    assert values["weights"] == str(weights)
    text = suggested.read_text()
    assert "precision 1.000, recall 0.600, 3 loops, 0 false" in text.replace("\n# ", " ")

    again = replay(bag, tmp_path / "b", suggested, weights)["evaluation"]
    assert (again["true_accepted"], again["false_accepted"]) == (3, 0)
    assert again["precision"] >= 0.99 and again["recall"] == expected["recall"]


def test_the_raw_curve_threshold_would_not_hold(tmp_path, weights):
    """What a threshold from the PR curve alone (precision 1.0 in (-1.49, -0.57]) gives here:
    a false loop, accepted by the sequence margin."""
    images, poses = revisit_world()
    bag = write_rosbag2(tmp_path / "bag", images, poses, pose_topic="/ground_truth")
    (tmp_path / "raw.yaml").write_text(SETTINGS.replace("-1000.0", "-0.6"))
    ev = replay(bag, tmp_path / "raw", tmp_path / "raw.yaml", weights)["evaluation"]
    assert (ev["true_accepted"], ev["false_accepted"]) == (5, 1)
