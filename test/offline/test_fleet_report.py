"""The demo fleet's summary.json: loops between robots and sessions judged against ground truth,
relocalisation, ATE per robot-session and the targets."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_posegraph_cli import write_odometry_bag

from pair_vpr_ros.errors import PoseGraphError
from pair_vpr_ros.offline.fleet_report import fleet_summary, main
from pair_vpr_ros.posegraph.transforms import planar_pose7

STAMPS = 100.0 + np.arange(40) / 10.0


def record(q: float, m: float, robot: str, session: str, accepted: bool = True) -> dict:
    return {"query_stamp": q, "match_stamp": m, "accepted": accepted, "match_robot": robot,
            "match_session": session}  # fmt: skip


@pytest.fixture
def fleet(tmp_path):
    """a/s1 drives x = 0..39 m; b/s1 the same line 1 m to the side; a/s2 the same line again.
    b finds a at its own x (true) and once 30 m off (false); a/s2 finds a/s1 from its third
    keyframe on."""
    line = {"a_s1": 0.0, "b_s1": 1.0, "a_s2": 0.0}
    drives = []
    for name, y in line.items():
        truth = np.array([planar_pose7(float(x), y, 0.0) for x in range(40)])
        write_odometry_bag(tmp_path / name, STAMPS, {"/ground_truth": truth})
        robot, session = name.split("_")
        drives.append({"robot": robot, "session": session, "bag": name})
    (tmp_path / "fleet.json").write_text(json.dumps({"drives": drives}))
    replays = {
        "a_s1": [record(STAMPS[i], STAMPS[0], "", "", accepted=False) for i in range(40)],
        "b_s1": [record(STAMPS[i], STAMPS[i], "a", "s1") for i in range(0, 40, 2)]
        + [record(STAMPS[39], STAMPS[0], "a", "s1")],
        "a_s2": [record(STAMPS[i], STAMPS[i], "a", "s1", accepted=i >= 2) for i in range(40)],
    }  # fmt: skip
    for name, records in replays.items():
        (tmp_path / "replay" / name).mkdir(parents=True)
        (tmp_path / "replay" / name / "loops.json").write_text(json.dumps(records))
    errors = {"odometry": {"ate_rmse": 2.0}, "optimised": {"ate_rmse": 0.3},
              "ate_in_reference_frame": 0.4}  # fmt: skip
    items = {n: {"joined": True, "loops_within": 0, "loops_between": 5, "errors": errors}
             for n in ("a/s1", "b/s1", "a/s2")}  # fmt: skip
    (tmp_path / "posegraph").mkdir()
    (tmp_path / "posegraph" / "posegraph.json").write_text(json.dumps({"trajectories": items}))
    return tmp_path


def test_summary_counts_and_targets(fleet, capsys):
    summary = fleet_summary(fleet)
    robot = summary["inter_robot"]
    assert (robot["true"], robot["false"], robot["possible"]) == (20, 1, 21 + 40)  # b, a/s2
    assert robot["precision"] == pytest.approx(20 / 21) and robot["recall"] == 20 / 61
    session = summary["inter_session"]
    assert (session["true"], session["false"], session["possible"]) == (38, 0, 40)
    assert summary["relocalisation"] == {
        "a/s2": {"keyframes_until_relocalised": 3, "keyframes_until_in_the_map": 3}
    }
    assert summary["all_in_one_frame"] and summary["trajectories"]["b/s1"]["ratio"] == 0.15
    assert summary["targets"] == {
        "inter_robot_precision>=0.95": True, "inter_robot_recall>=0.8": False,
        "relocalised_within_5_keyframes": True, "ate_ratio<=0.2": True, "ate<=0.5m": True,
        "all_in_one_frame_within_1m": True,
    }  # fmt: skip
    assert main([str(fleet)]) == 0
    assert json.loads((fleet / "summary.json").read_text()) == json.loads(json.dumps(summary))
    assert "inter_robot: 20 true, 1 false" in capsys.readouterr().out


def test_a_missing_replay_is_an_error(fleet):
    (fleet / "replay" / "b_s1" / "loops.json").unlink()
    with pytest.raises(PoseGraphError, match="no replay of b/s1: .*loops.json missing"):
        fleet_summary(fleet)
