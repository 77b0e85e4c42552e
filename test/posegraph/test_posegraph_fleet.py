"""The pose graph with several robot-sessions: key spaces, joining the first one's frame, loops
within and between trajectories, false loops between robots."""

from __future__ import annotations

from dataclasses import replace

import fleet_drives as fd
import gtsam
import numpy as np
import pytest
from drives import CAMERA

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.graph import PoseGraph
from pair_vpr_ros.posegraph.simulate import loop_covariance, make_factor
from pair_vpr_ros.posegraph.transforms import pose3

A, B, C = ("a", "s1"), ("b", "s1"), ("c", "s1")
SHIFT = 60  # robot b starts 60 frames (48 m) further along the rectangle


@pytest.fixture(scope="module")
def fleet():
    a, b = fd.robot(0, seed=1), fd.robot(SHIFT, seed=2)
    rng = np.random.default_rng(0)
    lap = a[3]
    within = fd.loops(a, a, A, A, 0, rng, start=lap) + fd.loops(b, b, B, B, 0, rng, start=lap)
    between = fd.loops(b, a, B, A, SHIFT, rng, start=100)
    return a, b, within, between


def config(**kw) -> PoseGraphConfig:
    return PoseGraphConfig(camera_to_base=CAMERA, **kw)


def test_keys_per_robot_session_are_stable():
    graph = PoseGraph(config(), [A, B, ("a", "s2")])
    assert [t.char for t in graph.tracks] == ["x", "a", "b"]
    for trajectory in (A, B):
        graph.add_odometry(1.0, (0, 0, 0, 0, 0, 0, 1), trajectory)
    assert graph.tracks.get(B).nodes[0].key == gtsam.symbol("a", 0)
    assert graph.tracks.get(A).nodes[0].key == gtsam.symbol("x", 0)
    assert graph.joined(A) and not graph.joined(B)


def test_fleet_ends_in_one_frame(fleet):
    a, b, within, between = fleet
    graph = PoseGraph(config(), [A, B])
    fd.feed(graph, {A: a, B: b}, within + between)
    assert graph.joined(B) and not graph.waiting and not graph.counts.skipped
    assert graph.counts.loops_added == len(within) + len(between)
    assert fd.world_error(graph, A, a, a) < 0.6
    assert fd.world_error(graph, B, b, a) < 0.6  # in a's frame, with no alignment of its own
    assert graph.loop_inliers().all()


def test_a_trajectory_without_loops_to_the_others_stays_out(fleet):
    a, b, within, _ = fleet
    graph = PoseGraph(config(), [A, B])
    fd.feed(graph, {A: a, B: b}, within)
    assert not graph.joined(B)
    np.testing.assert_allclose(graph.optimised_poses(B), graph.odometry_poses(B))
    assert graph.map_to_odom(B).equals(gtsam.Pose3(), 1e-12)
    waiting = sum(lp.query_robot == "b" for lp in within)
    assert graph.counts.skipped == {"loop: a trajectory it touches never joined": waiting}
    assert graph.counts.loops_added == len(within) - waiting


def test_a_lone_false_loop_between_robots_does_not_place_a_robot(fleet):
    """The first loop between a and b is false (b claims to be 2 m from a place 60 m away);
    with join_min_loops=2 b joins on the true loops that follow, and the false one ends an
    outlier. With join_min_loops=1 it would have placed b by the false loop."""
    a, b, within, between = fleet
    first = between[0]
    wrong = replace(first, match_stamp=float(a[0][(100 + SHIFT + 75) % a[3]]),
                    query_stamp=first.query_stamp - 0.5)  # fmt: skip
    wrong = replace(wrong, translation=(0.0, 0.0, 2.0), rotation=(0.0, 0.0, 0.0, 1.0))
    graph = PoseGraph(config(), [A, B])
    fd.feed(graph, {A: a, B: b}, within + between + [wrong])
    assert graph.joined(B)
    assert fd.world_error(graph, B, b, a) < 0.6
    inliers = graph.loop_inliers()
    assert [e.factor for e, ok in zip(graph.loops, inliers, strict=True) if not ok] == [wrong]


def test_loops_naming_unknown_or_merged_robots_are_counted(fleet):
    a, b, within, between = fleet
    graph = PoseGraph(config(), [A, B])
    stranger = replace(between[0], match_robot="c")
    nameless = replace(between[1], query_robot="", query_session="")
    fd.feed(graph, {A: a, B: b}, [stranger, nameless])
    assert graph.counts.skipped == {
        "loop: robot-session c/s1 is not in the graph": 1,
        "loop: robot-session */* is not in the graph": 1,
    }
    single = PoseGraph(config())
    for stamp, pose in zip(a[0][:50], a[2][:50], strict=True):
        single.add_odometry(float(stamp), tuple(pose))
    loop = make_factor(a[0][40], a[0][0], pose3((0, 0, 0, 0, 0, 0, 1)), loop_covariance())
    assert single.add_loop(replace(loop, query_robot="a", match_robot="a")) == "added"
    reason = single.add_loop(replace(loop, query_robot="a", match_robot="b"))
    assert reason == (
        "loop between robot-sessions a/* and b/* falls on one trajectory (*/*): give each its own"
    )


def test_wildcard_session_takes_any_session_of_its_robot():
    graph = PoseGraph(config(), [("a", ""), ("b", "")])
    assert graph.tracks.resolve("a", "20261125T120000Z").trajectory == ("a", "")
    assert graph.tracks.resolve("c", "x") == (
        "robot-session c/x is not in the graph (trajectories: a/*, b/*)"
    )


@pytest.mark.parametrize(
    ("trajectories", "message"),
    [
        ([A, B, A], "trajectory a/s1 is given twice: each robot-session needs its own"),
        ([A, ("a", 3)], "trajectory ('a', 3): robot and session must be strings"),
    ],
)
def test_bad_trajectory_lists(trajectories, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        PoseGraph(config(), trajectories)


def test_unknown_trajectory_of_odometry_is_an_error():
    graph = PoseGraph(config(), [A])
    with pytest.raises(ConfigError, match="trajectory c/s1 is not in the pose graph"):
        graph.add_odometry(1.0, (0, 0, 0, 0, 0, 0, 1), C)


@pytest.mark.parametrize(
    ("name", "value", "reason"),
    [
        ("join_min_loops", 0, "join_min_loops=0 must be 1-100"),
        ("join_tolerance_m", 0.0, "join_tolerance_m=0.0 must be a positive number"),
        ("join_tolerance_per_m", -1.0, "join_tolerance_per_m=-1.0 must be a number >= 0"),
    ],
)
def test_bad_join_settings(name, value, reason):
    with pytest.raises(ConfigError, match=reason):
        PoseGraphConfig(**{name: value}).validate()
