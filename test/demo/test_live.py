"""demo.live (make demo-live) without starting anything: make demo's loops read back, the live
loops compared by their stamps, and LAUNCH=1 without `ros2` one clear usage error."""

from __future__ import annotations

import pytest

from pair_vpr_ros.demo import live
from pair_vpr_ros.errors import UsageError

HEADER = "query_stamp,match_stamp,accepted,tx\n"


def test_make_demos_loops_and_factors_are_read_back(tmp_path):
    (tmp_path / "loops.csv").write_text(
        HEADER + "10.1,1.0,True,0.5\n10.2,1.1,True,nan\n10.3,1.2,False,0.1\n10.4,1.3,True,\n"
    )
    pairs, factors = live.replay_loops(tmp_path)
    assert pairs == {(10.1, 1.0), (10.2, 1.1), (10.4, 1.3)}
    assert factors == 1  # only accepted loops with a relative pose become factors


def test_live_loops_are_the_accepted_records_by_stamp():
    records = [
        {"query_stamp": 10.1000001, "match_stamp": 1.0, "accepted": True},
        {"query_stamp": 10.3, "match_stamp": 1.2, "accepted": False},
    ]
    assert live.live_loops(records) == {(10.1, 1.0)}


def test_launch_without_ros2_on_path_is_a_usage_error(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(UsageError) as err:
        live.start_nodes(live.demo_arguments("/m.pth", "/p.yaml"), tmp_path, True, {})
    assert str(err.value) == (
        "LAUNCH=1 needs `ros2 launch` on PATH (a ROS install, or the environment of "
        "scripts/ros_cli_env.sh, docs/launch.md)"
    )
