"""Prior sessions in the pose graph (posegraph.priors): a saved map's keyframe poses become a
trajectory, the map frame, and a live robot's loops into those keyframes place it there."""

from __future__ import annotations

import fleet_drives as fd
import numpy as np
import pytest
from map_fixtures import prior_drive_map, save_keyframes

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.graph import PoseGraph
from pair_vpr_ros.posegraph.priors import graph_with_priors, read_prior_sessions
from pair_vpr_ros.posegraph.transforms import pose3

CONFIG = PoseGraphConfig(camera_to_base=fd.CAMERA)
A, B = ("a", "day1"), ("b", "s1")  # the prior session, the live robot


def feed_live(graph, trajectory, drive, loops) -> list[str]:
    """The live robot's odometry, each loop once its query stamp is reached; the answers."""
    answers, k = [], 0
    for stamp, pose in zip(drive[0], drive[2], strict=True):
        graph.add_odometry(float(stamp), tuple(pose), trajectory)
        while k < len(loops) and loops[k].query_stamp <= stamp:
            answers.append(graph.add_loop(loops[k]))
            k += 1
        graph.update()
    graph.finish()
    return answers


def test_read_prior_sessions_exact(tmp_path):
    first = save_keyframes(tmp_path / "m1", [
        (12.0, (2, 0, 0, 0, 0, 0, 1), "a", "day1"),
        (10.0, (0, 0, 0, 0, 0, 0, 1), "a", "day1"),
        (5.0, (7, 1, 0, 0, 0, 0, 1), "b", "day1"),
        (11.0, None, "a", "day1"),
        (13.0, (3, 0, 0, 0, 0, 0, 1), "", ""),
    ])  # fmt: skip
    second = save_keyframes(tmp_path / "m2", [
        (12.0, (9, 9, 0, 0, 0, 0, 1), "a", "day1"),  # the same session in two maps
        (14.0, (4, 0, 0, 0, 0, 0, 1), "a", "day1"),
        (1.0, (0, 0, 0, 0, 0, 0, 0), "c", "day1"),  # a zero quaternion
    ])  # fmt: skip
    priors = read_prior_sessions([first, second])
    assert priors.trajectories == [("a", "day1"), ("b", "day1")]
    a, b = priors.sessions
    assert a.stamps.tolist() == [10.0, 12.0, 14.0]
    assert a.poses[:, 0].tolist() == [0.0, 2.0, 4.0]  # 12.0 s: the first map's keyframe
    assert a.maps == [str(tmp_path / "m1"), str(tmp_path / "m2")]
    assert (b.stamps.tolist(), b.poses.tolist()) == ([5.0], [[7, 1, 0, 0, 0, 0, 1]])
    assert priors.skipped == {
        "prior keyframe: no pose": 1,
        "prior keyframe: no robot or session (a loop cannot name it)": 1,
        "prior keyframe: stamp of another keyframe of its session": 1,
        "prior keyframe: pose has a zero quaternion": 1,
    }
    assert priors.notes == [f"prior_map_dirs: {tmp_path / 'm1'}: 5 keyframes",
                            f"prior_map_dirs: {tmp_path / 'm2'}: 3 keyframes"]  # fmt: skip


def test_the_first_prior_session_is_the_map_frame_and_its_poses_the_odometry(tmp_path):
    drive = fd.robot(0, seed=1, laps=1)
    priors = read_prior_sessions([prior_drive_map(tmp_path / "a", drive, without_pose={5, 9})])
    graph = graph_with_priors(CONFIG, priors, [B])
    assert [t.trajectory for t in graph.tracks] == [A, B]
    assert graph.joined(A) and not graph.joined(B)
    assert graph.counts.odometry == len(drive[0]) - 2
    assert graph.counts.skipped == {"prior keyframe: no pose": 2}
    # The map frame is the prior session's odometry frame: its first node stays where it was.
    assert np.allclose(graph.optimised_poses(A)[0], drive[2][0], atol=1e-6)


def test_a_live_loop_into_a_prior_keyframe_is_added_and_places_the_robot(tmp_path):
    a, b = fd.robot(0, seed=1, laps=1), fd.robot(60, seed=2, laps=1)
    loops = fd.loops(b, a, B, A, 60, np.random.default_rng(0), every=5)
    priors = read_prior_sessions([prior_drive_map(tmp_path / "a", a)])
    graph = graph_with_priors(CONFIG, priors, [B])
    answers = feed_live(graph, B, b, loops)
    assert set(answers) <= {"added", "waiting"} and answers.count("added") >= 1
    assert graph.counts.loops_added == len(loops) and not graph.counts.skipped
    assert graph.joined(B)
    # b's corrected poses land in the prior session's frame (a's start), within a metre ...
    assert fd.world_error(graph, B, b, a) < 1.0
    # ... where its odometry (its own frame) was tens of metres off.
    to_map = pose3(a[1][0]).inverse()
    index = np.searchsorted(b[0], graph.node_stamps(B))
    truth = np.array([to_map.compose(pose3(b[1][i])).translation()[:2] for i in index])
    assert np.sqrt(np.mean(np.sum((b[2][index, :2] - truth) ** 2, axis=1))) > 10.0
    # Without the prior map, the same loops are counted skips (the gap this closes).
    alone = PoseGraph(CONFIG, [B])
    feed_live(alone, B, b, loops)
    assert alone.counts.loops_added == 0
    assert alone.counts.skipped == {"loop: robot-session a/day1 is not in the graph": len(loops)}


def test_a_single_live_robot_joins_the_prior_frame(tmp_path):
    """The single-robot form (trajectory ("", "")): its loops into the prior session name it
    by robot and session, the wildcard takes them."""
    a, b = fd.robot(0, seed=1, laps=1), fd.robot(60, seed=2, laps=1)
    loops = fd.loops(b, a, B, A, 60, np.random.default_rng(0), every=5)
    graph = graph_with_priors(CONFIG, read_prior_sessions([prior_drive_map(tmp_path / "a", a)]),
                              [("", "")])  # fmt: skip
    feed_live(graph, ("", ""), b, loops)
    assert graph.counts.loops_added == len(loops) and graph.joined(("", ""))
    assert fd.world_error(graph, ("", ""), b, a) < 1.0


def test_a_prior_session_that_is_also_live_is_refused(tmp_path):
    path = save_keyframes(tmp_path / "m", [(1.0, (0, 0, 0, 0, 0, 0, 1), "a", "day1")])
    with pytest.raises(ConfigError) as err:
        graph_with_priors(CONFIG, read_prior_sessions([path]), [("a", "day1")])
    assert str(err.value) == (
        f"trajectories: robot-session a/day1 is a prior session (in {tmp_path / 'm'}): a session "
        "id names one recording, so give the live robot a new session id (or leave SESSION empty)"
    )
    # Another session of the same robot, or any session of it, is a live robot of its own.
    graph = graph_with_priors(CONFIG, read_prior_sessions([path]), [("a", "day2")])
    assert [t.trajectory for t in graph.tracks] == [("a", "day1"), ("a", "day2")]
