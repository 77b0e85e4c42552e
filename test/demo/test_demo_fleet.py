"""The demo fleet: overlapping routes and clocks, a second session a day later in another light,
odometry from each robot's own origin."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pair_vpr_ros.demo.fleet import DAY_NS, FLEET, fleet_worlds, write_fleet_bags
from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.posegraph.single import PoseGraphSummary, read_track


def test_drives_overlap_in_place_and_time():
    worlds = fleet_worlds(seed=7, frames=60, size=(32, 24))
    assert [(d.robot, d.session) for d, _ in worlds] == [
        ("a", "day1"), ("b", "day1"), ("c", "day1"), ("a", "day2")
    ]  # fmt: skip
    (_, a), (_, b), (_, c), (_, a2) = worlds
    assert a.stamps_ns[0] == b.stamps_ns[0] == c.stamps_ns[0]  # one clock, one start
    assert a2.stamps_ns[0] == a.stamps_ns[0] + DAY_NS
    # b starts where a is a third of its drive later: the routes overlap
    np.testing.assert_allclose(b.poses[0], a.poses[20])
    assert np.min(np.linalg.norm(a.poses[:, :2] - a2.poses[0, :2], axis=1)) < 6.0  # a revisit
    assert a2.lighting_of(0).name == "dusk" and a.lighting_of(0).name == "day"
    assert {d.lightings[0].name for d in FLEET[:3]} == {"day", "dusk", "overcast"}
    with pytest.raises(ConfigError, match="frames=10 per drive must be at least 24"):
        fleet_worlds(frames=10)


@pytest.mark.slow
def test_bags_have_the_robot_topics_and_local_odometry(tmp_path):
    manifest = write_fleet_bags(tmp_path, seed=7, frames=24, size=(32, 24))
    drives = json.loads(manifest.read_text())["drives"]
    assert [d["bag"] for d in drives] == ["a_day1.mcap", "b_day1.mcap", "c_day1.mcap",
                                          "a_day2.mcap"]  # fmt: skip
    with open_bag(tmp_path / "b_day1.mcap") as reader:
        assert {"/camera/image_raw", "/camera/camera_info", "/camera/depth/image_raw", "/odom",
                "/ground_truth"} <= set(reader.topics)  # fmt: skip
        odom = read_track(reader, "/odom", "odometry", PoseGraphSummary())
        truth = read_track(reader, "/ground_truth", "ground truth", PoseGraphSummary())
    np.testing.assert_allclose(odom.poses[0], [0, 0, 0, 0, 0, 0, 1], atol=1e-12)
    assert np.linalg.norm(truth.poses[0, :2]) > 1.0  # the world frame is elsewhere
    assert len(odom) == len(truth) == 24
