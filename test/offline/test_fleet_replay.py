"""`run_fleet` / `pairvpr-fleet-replay`: robots replayed together with the exchange, on the tiny
network (only exact image repeats are loops: exact_match.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from exact_match import EXACT_MATCH
from synthetic_data import write_rgb

from pair_vpr_ros.fleet import Faults
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.offline.fleet.cli import main
from pair_vpr_ros.offline.fleet.replay import FleetRobot, run_fleet, write_fleet_run

CONFIG = dict(EXACT_MATCH, keyframe_max_similarity=0.99999)


@pytest.fixture(scope="module")
def places():
    rng = np.random.default_rng(11)
    return [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(10)]


def frames(places, order, t0):
    return [Frame(t0 + i, places[p], frame_id="cam") for i, p in enumerate(order)]


def test_three_robots_on_overlapping_clocks(tiny_model, places, tmp_path):
    robots = [
        FleetRobot("a", "s1", frames(places, [0, 1, 2, 3], 100.0)),
        FleetRobot("b", "s1", frames(places, [4, 5, 1, 6], 100.5)),  # 1: a's, 2 s earlier
        FleetRobot("c", "s9", frames(places, [7, 8, 6, 3], 101.2)),  # 6 and 3: seen by b, a
    ]
    run = run_fleet(robots, tiny_model, DetectorConfig(**CONFIG), {"budget": 10})
    found = sorted(
        (x.query_robot, x.record.query_id, x.match_robot, x.record.match_id) for x in run.loops
    )
    # place 6: c at 103.2 s, b at 103.5 s, so b asks c; place 3: a at 103 s, c at 104.2 s
    assert found == [("b", 2, "a", 1), ("b", 3, "c", 2), ("c", 3, "a", 3)]
    assert all(x.record.accepted for x in run.loops)
    t = run.totals()
    assert (t["keyframes"], t["inter_robot_loops"], t["inter_robot_rejected"]) == (12, 3, 0)
    assert t["descriptor_bytes_per_keyframe"] == t["bytes_sent"]["keyframes"] / 12 < 1536
    assert (
        t["scoring_bytes_per_accepted_loop"]
        == (t["bytes_sent"]["request"] + t["bytes_sent"]["response"]) / 3
    )
    out = write_fleet_run(run, tmp_path / "fleet")
    loops = json.loads((out / "inter_robot_loops.json").read_text())
    assert [(x["query_robot"], x["match_session"]) for x in loops] == [
        ("b", "s1"), ("b", "s9"), ("c", "s1"),
    ]  # fmt: skip
    summary = json.loads((out / "fleet_summary.json").read_text())
    assert summary["robots"]["c"]["peer_keyframes"] == {"a/s1": 4, "b/s1": 4}
    own = json.loads((out / "a" / "loops.json").read_text())  # a's decisions: none accepted
    assert len(own) == 1 and not own[0]["accepted"]  # the others: all too recent
    assert {(r["query_robot"], r["match_session"]) for r in own} == {("a", "s1")}


def test_a_lossy_network_loses_loops_not_the_run(tiny_model, places):
    robots = [
        FleetRobot("a", "s1", frames(places, list(range(10)), 0.0)),
        FleetRobot("b", "s1", frames(places, list(range(10)), 20.0)),
    ]
    run = run_fleet(robots, tiny_model, DetectorConfig(**CONFIG), {"budget": 100},
                    faults=Faults(drop=0.3, duplicate=0.2, reorder=0.2, seed=1))  # fmt: skip
    assert 0 < len(run.loops) < 10 and run.dropped > 0
    ex = run.exchanges["b"]
    assert ex["keyframes"] == 10 and ex["peer_missing"] > 0


def test_the_command_line_on_two_image_folders(places, tmp_path, capsys):
    for robot, order in (("a", [0, 1, 2]), ("b", [3, 1])):
        for i, p in enumerate(order):
            write_rgb(tmp_path / robot / f"{i:03d}.png", places[p])
    params = tmp_path / "fleet.yaml"
    lines = [f"    {k}: {v}" for k, v in CONFIG.items()]
    params.write_text("/**:\n  ros__parameters:\n" + "\n".join(lines) + "\n")
    argv = ["--robot", "a", "s1", str(tmp_path / "a"), "--robot", "b", "s2", str(tmp_path / "b"),
            "--weights", "random-tiny", "--params-file", str(params), "--quiet", "--out",
            str(tmp_path / "out")]  # fmt: skip
    assert main(argv) == 0
    assert "5 keyframes, 1 inter-robot loops (0 rejected)" in capsys.readouterr().out
    loops = json.loads((tmp_path / "out" / "inter_robot_loops.json").read_text())
    assert [(x["query_robot"], x["query_id"], x["match_robot"], x["match_id"]) for x in loops] == [
        ("b", 1, "a", 1)
    ]
