"""The demo fleet's summary.json: loops between robots and sessions judged against ground truth,
relocalisation, ATE per robot-session and the targets."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_posegraph_cli import write_odometry_bag

from pair_vpr_ros.errors import PoseGraphError
from pair_vpr_ros.offline.fleet import loops as fleet_loops
from pair_vpr_ros.offline.fleet.report import fleet_summary, main
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


def test_relocalisation_counts_keyframes_not_loops(fleet):
    # loop_per_map: a keyframe may have a loop into each map; b/s1's comes first here
    per_map = []
    for i in range(40):
        per_map += [record(STAMPS[i], STAMPS[i], "b", "s1"),
                    record(STAMPS[i], STAMPS[i], "a", "s1", accepted=i >= 2)]  # fmt: skip
    (fleet / "replay" / "a_s2" / "loops.json").write_text(json.dumps(per_map))
    summary = fleet_summary(fleet)
    assert summary["relocalisation"] == {
        "a/s2": {"keyframes_until_relocalised": 3, "keyframes_until_in_the_map": 1}
    }  # records: the 6th is the first true loop into a/s1, of the 3rd keyframe
    assert (summary["inter_session"]["true"], summary["inter_robot"]["true"]) == (38, 20 + 40)


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
        "all_in_one_frame_within_1m": True, "descriptor_bytes_per_keyframe<=1536": False,
    }  # fmt: skip
    assert summary["exchange"] is None and summary["bytes_per_keyframe"] is None
    assert summary["notes"] == [
        "no fleet exchange (exchange/inter_robot_loops.json): bytes not measured"
    ]
    assert main([str(fleet)]) == 0
    assert json.loads((fleet / "summary.json").read_text()) == json.loads(json.dumps(summary))
    assert "inter_robot: 20 true, 1 false" in capsys.readouterr().out


def test_a_missing_replay_is_an_error(fleet):
    (fleet / "replay" / "b_s1" / "loops.json").unlink()
    with pytest.raises(PoseGraphError, match="no replay of b/s1: .*loops.json missing"):
        fleet_summary(fleet)


def decision(q: tuple, m: tuple, accepted: bool = True) -> dict:
    """An exchange decision: query (robot, session, frame index) scored against match's."""
    return {"query_robot": q[0], "query_session": q[1], "query_stamp": STAMPS[q[2]],
            "match_robot": m[0], "match_session": m[1], "match_stamp": STAMPS[m[2]],
            "accepted": accepted}  # fmt: skip


@pytest.fixture
def exchange(fleet):
    """a/s1 and b/s1 exchanged: one pair b's replay found already (asked the other way round),
    a new true one from a (no prior drive: not in recall), a new true one from b at its last
    keyframe (its replay took a false match there), a new false one, one rejected."""
    loops = [
        decision(("a", "s1", 0), ("b", "s1", 0)),
        decision(("a", "s1", 1), ("b", "s1", 1)),
        decision(("b", "s1", 39), ("a", "s1", 39)),
        decision(("a", "s1", 0), ("b", "s1", 30)),
        decision(("b", "s1", 5), ("a", "s1", 5), accepted=False),
    ]
    (fleet / "exchange").mkdir()
    (fleet / "exchange" / "inter_robot_loops.json").write_text(json.dumps(loops))
    totals = {"keyframes": 80, "bytes_sent": {"keyframes": 86000, "request": 33000,
              "response": 400}, "inter_robot_loops": 4, "inter_robot_rejected": 1,
              "descriptor_bytes_per_keyframe": 1075.0, "bytes_per_keyframe": 1492.5,
              "scoring_bytes_per_accepted_loop": 8350.0, "dropped_by_bus": 0}  # fmt: skip
    summary = {"totals": totals, "robots": {}}
    (fleet / "exchange" / "fleet_summary.json").write_text(json.dumps(summary))
    return fleet


def test_exchange_loops_add_each_pair_once(exchange, capsys):
    assert fleet_loops.main([str(exchange)]) == 0
    added = json.loads((exchange / "exchange" / "added_loops.json").read_text())
    assert [(r["query_robot"], r["query_stamp"], r["match_stamp"]) for r in added] == [
        ("a", STAMPS[1], STAMPS[1]), ("b", STAMPS[39], STAMPS[39]), ("a", STAMPS[0], STAMPS[30])
    ]  # fmt: skip
    assert "3 of 4 accepted exchange loops added (1 pairs found by a replay already)" in (
        capsys.readouterr().out
    )


def test_summary_with_the_exchange(exchange):
    summary = fleet_summary(exchange)
    assert summary["exchange"] == {
        "accepted": 4, "true": 3, "false": 1, "precision": 0.75, "added_to_graph": 3,
        "found_by_a_replay_too": 1, "keyframes": 80,
        "bytes_sent": {"keyframes": 86000, "request": 33000, "response": 400},
        "descriptor_bytes_per_keyframe": 1075.0, "bytes_per_keyframe": 1492.5,
        "scoring_bytes_per_accepted_loop": 8350.0, "bytes_per_accepted_loop": 29850.0,
    }  # fmt: skip
    assert summary["bytes_per_keyframe"] == {"descriptors": 1075.0, "all": 1492.5}
    assert summary["bytes_per_accepted_loop"] == {"scoring": 8350.0, "all": 29850.0}
    robot = summary["inter_robot"]  # the replays' 20 + 1 and the 2 true + 1 false added
    assert (robot["true"], robot["false"], robot["possible"]) == (22, 2, 61)
    assert robot["precision"] == 22 / 24 and robot["recall"] == 21 / 61  # b's keyframe 39 found
    assert summary["targets"]["descriptor_bytes_per_keyframe<=1536"] and summary["notes"] == []


def test_exchange_without_its_summary_is_an_error(exchange):
    (exchange / "exchange" / "fleet_summary.json").unlink()
    with pytest.raises(PoseGraphError, match="fleet exchange without its summary: .* missing"):
        fleet_summary(exchange)


def test_added_loops_need_an_exchange(fleet, capsys):
    assert fleet_loops.main([str(fleet)]) == 1
    assert "error: no fleet exchange in " in capsys.readouterr().err
