"""The GTSAM pose graph: conversions, drift removal, false loops, bad input."""

from __future__ import annotations

import math
from dataclasses import replace

import drives
import gtsam
import numpy as np
import pytest
from drives import CAMERA

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.messages.factor import LoopFactor
from pair_vpr_ros.posegraph.config import MAX_PENDING, PoseGraphConfig
from pair_vpr_ros.posegraph.graph import PoseGraph
from pair_vpr_ros.posegraph.simulate import (
    false_loops,
    ground_truth_loops,
    loop_covariance,
    make_factor,
)
from pair_vpr_ros.posegraph.transforms import planar_pose7, pose3, pose7, transform_covariance


@pytest.fixture(scope="module")
def drive():
    return drives.drive()


def run(stamps, odometry, loops, config=None) -> PoseGraph:
    graph = PoseGraph(config)
    order = sorted(loops, key=lambda lp: lp.query_stamp)
    k = 0
    for stamp, pose in zip(stamps, odometry, strict=True):
        graph.add_odometry(float(stamp), tuple(pose))
        while k < len(order) and order[k].query_stamp <= stamp:
            graph.add_loop(order[k])
            k += 1
        graph.update()
    graph.finish()
    return graph


def position_rmse(graph: PoseGraph, poses: np.ndarray, stamps, truth) -> float:
    index = np.searchsorted(stamps, graph.node_stamps())
    return float(np.sqrt(np.mean(np.sum((poses[:, :2] - truth[index, :2]) ** 2, axis=1))))


# ---- conversions ----------------------------------------------------------------------------
def loop(query: float, match: float, pose=(0, 0, 0, 0, 0, 0, 1), cov=None) -> LoopFactor:
    cov = loop_covariance() if cov is None else cov
    return make_factor(query, match, pose3(pose), np.asarray(cov))


def test_loop_covariance_reaches_the_axis_ros_names():
    """A loop sure of everything but x (ROS order x, y, z, rx, ry, rz; the match camera's axes):
    the graph must move the query node along x only. The match frame is turned 90 deg from the
    query's, so a covariance read in the wrong frame or order frees the wrong axis."""
    cov = np.diag([100.0, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8])
    graph = PoseGraph(PoseGraphConfig(loop_kernel="none", node_spacing_m=0.5))
    for i in range(30):  # along +x, heading +x; at node 5 the robot stood turned by +90 deg
        yaw = math.pi / 2 if i == 5 else 0.0
        graph.add_odometry(float(i), planar_pose7(0.5 * i, 0.0, yaw))
    # True T_match_query: 12 m along the match frame's -y (its y is world -x), turned -90 deg.
    # Claimed: also 2 m along its -x (world -y), which only a loose x can absorb.
    claimed = pose3((-2.0, -12.0, 0.0, *planar_pose7(0, 0, -math.pi / 2)[3:]))
    assert graph.add_loop(make_factor(29.0, 5.0, claimed, cov)) == "added"
    graph.update()
    last = graph.optimised_poses()[-1]
    assert last[1] == pytest.approx(0.0, abs=0.05)  # the loop's tight axis: odometry's value
    assert last[0] == pytest.approx(14.5, abs=0.05)  # the loose axis: odometry's value too
    # Now the loop is tight along x (its 2 m offset wins) and loose along y.
    graph = PoseGraph(PoseGraphConfig(loop_kernel="none", node_spacing_m=0.5))
    for i in range(30):
        yaw = math.pi / 2 if i == 5 else 0.0
        graph.add_odometry(float(i), planar_pose7(0.5 * i, 0.0, yaw))
    tight_x = np.diag([1e-6, 100.0, 1e-6, 1e-8, 1e-8, 1e-8])
    graph.add_loop(make_factor(29.0, 5.0, claimed, tight_x))
    graph.update()
    last = graph.optimised_poses()[-1]
    assert last[1] == pytest.approx(-2.0, abs=0.05)  # match-frame -x is world -y here
    assert last[0] == pytest.approx(14.5, abs=0.05)


def test_pose_conversions_round_trip():
    p = (1.0, -2.0, 0.5, 0.1, -0.2, 0.3, 0.9)
    n = np.linalg.norm(p[3:])
    back = pose7(pose3(p))
    np.testing.assert_allclose(back, [*p[:3], *(np.array(p[3:]) / n)], atol=1e-12)
    yaw = pose3(planar_pose7(0.0, 0.0, 2.0)).rotation().yaw()
    assert yaw == pytest.approx(2.0)


def test_transform_covariance_rotates_translation_noise():
    cov = np.diag([1e-4, 1e-4, 1e-4, 1.0, 0.0, 0.0])  # GTSAM order: noise along x only
    turned = transform_covariance(cov, gtsam.Pose3(gtsam.Rot3.Rz(math.pi / 2), np.zeros(3)))
    np.testing.assert_allclose(np.diag(turned)[3:], [0.0, 1.0, 0.0], atol=1e-12)


# ---- drift removal --------------------------------------------------------------------------
def test_loops_remove_most_of_the_drift(drive):
    stamps, truth, odometry, pairs = drive
    loops = ground_truth_loops(stamps, truth, pairs, np.random.default_rng(0),
                               loop_covariance(0.1, 1.0), camera_to_base=CAMERA)  # fmt: skip
    graph = run(stamps, odometry, loops, PoseGraphConfig(camera_to_base=CAMERA))
    before = position_rmse(graph, graph.odometry_poses(), stamps, truth)
    after = position_rmse(graph, graph.optimised_poses(), stamps, truth)
    assert graph.counts.loops_added == len(loops) and not graph.counts.skipped
    assert before > 5.0, before
    assert after < before / 10, (before, after)
    assert graph.loop_inliers().mean() > 0.95


def test_false_loops_are_down_weighted_not_followed(drive):
    stamps, truth, odometry, pairs = drive
    rng = np.random.default_rng(1)
    cov = loop_covariance(0.1, 1.0)
    loops = ground_truth_loops(stamps, truth, pairs, rng, cov, camera_to_base=CAMERA)
    wrong = false_loops(stamps, truth, len(loops) // 10, rng, covariance=cov,
                        camera_to_base=CAMERA)  # fmt: skip
    graph = run(stamps, odometry, loops + wrong, PoseGraphConfig(camera_to_base=CAMERA))
    before = position_rmse(graph, graph.odometry_poses(), stamps, truth)
    after = position_rmse(graph, graph.optimised_poses(), stamps, truth)
    assert after < before / 5, (before, after)
    inliers = graph.loop_inliers()
    is_false = np.array([any(e.factor is w for w in wrong) for e in graph.loops])
    assert is_false.sum() == len(wrong)
    assert not inliers[is_false].any() and inliers[~is_false].mean() > 0.95
    # Without a robust kernel the same false loops bend the trajectory far more.
    plain = run(stamps, odometry, loops + wrong,
                PoseGraphConfig(camera_to_base=CAMERA, loop_kernel="none"))  # fmt: skip
    assert position_rmse(plain, plain.optimised_poses(), stamps, truth) > 3 * after


def test_camera_extrinsic_is_applied(drive):
    """Loops between optical camera frames give the drive's result only with the extrinsic."""
    stamps, truth, odometry, pairs = drive
    loops = ground_truth_loops(stamps, truth, pairs, np.random.default_rng(0),
                               loop_covariance(0.01, 0.1), camera_to_base=CAMERA)  # fmt: skip
    right = run(stamps, odometry, loops, PoseGraphConfig(camera_to_base=CAMERA))
    wrong = run(stamps, odometry, loops, PoseGraphConfig())
    assert position_rmse(right, right.optimised_poses(), stamps, truth) < 0.5
    assert position_rmse(wrong, wrong.optimised_poses(), stamps, truth) > 2.0


def test_map_to_odom_maps_the_newest_odometry_pose_onto_the_optimised_one(drive):
    stamps, truth, odometry, pairs = drive
    loops = ground_truth_loops(stamps, truth, pairs, np.random.default_rng(0),
                               camera_to_base=CAMERA)  # fmt: skip
    graph = run(stamps, odometry, loops, PoseGraphConfig(camera_to_base=CAMERA))
    corrected = graph.map_to_odom().compose(pose3(graph.odometry_poses()[-1]))
    np.testing.assert_allclose(pose7(corrected), graph.optimised_poses()[-1], atol=1e-9)
    assert np.linalg.norm(graph.map_to_odom().translation()) > 1.0


# ---- bad input ------------------------------------------------------------------------------
def test_bad_odometry_is_skipped_and_counted():
    graph = PoseGraph()
    assert graph.add_odometry(1.0, planar_pose7(0, 0, 0)) is None
    nan = (math.nan, 0, 0, 0, 0, 0, 1)
    assert graph.add_odometry(2.0, nan) == "pose has NaN or infinite values"
    assert graph.add_odometry(2.0, (1, 0, 0, 0, 0, 0, 0)) == "pose has a zero quaternion"
    assert graph.add_odometry(0.5, planar_pose7(1, 0, 0)) == (
        "odometry stamp not after the previous one"
    )
    assert graph.add_odometry(math.inf, planar_pose7(1, 0, 0)) == "stamp is not finite"
    assert graph.add_odometry(9.0, planar_pose7(2, 0, 0)) is None  # a 7 s gap
    assert graph.counts.odometry == 2 and graph.counts.odometry_gaps == 1
    assert sum(graph.counts.skipped.values()) == 4 and graph.counts.nodes == 2
    graph.update()
    assert graph.optimised_poses().shape == (2, 7)


def test_loops_that_cannot_be_placed_are_skipped_with_a_reason():
    graph = PoseGraph(PoseGraphConfig(stamp_tolerance_s=0.2))
    cov = loop_covariance()
    identity = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    # make_factor cannot build a zero quaternion: build that factor directly
    zero_q = replace(loop(20.0, 12.0), rotation=(0.0, 0.0, 0.0, 0.0))
    assert graph.add_loop(loop(5.0, 1.0, identity, cov)) == "no odometry yet"
    for i in range(20):
        graph.add_odometry(10.0 + i, planar_pose7(2.0 * i, 0, 0))
    graph.add_odometry(60.0, planar_pose7(50.0, 0, 0))  # gap 29 s -> 60 s
    assert graph.add_loop(loop(15.0, 2.0, identity, cov)) == (
        "stamp before the odometry history (2.000 s < 10.000 s)"
    )
    assert graph.add_loop(loop(45.0, 12.0, identity, cov)) == (
        "stamp in an odometry gap (45.000 s, between 29.000 s and 60.000 s)"
    )
    assert graph.add_loop(loop(60.5, 12.0, identity, cov)) == "pending"
    bad = cov.copy()
    bad[0, 0] = math.nan
    assert graph.add_loop(loop(20.0, 12.0, identity, bad)) == (
        "covariance has NaN or infinite values"
    )
    assert graph.add_loop(loop(20.0, 12.0, identity, -cov)) == (
        "covariance is not positive definite"
    )
    assert graph.add_loop(loop(20.0, 20.05, identity, cov)) == (
        "both loop stamps fall on the same graph node"
    )
    assert graph.add_loop(zero_q) == ("transform: pose has a zero quaternion")
    assert graph.add_loop(loop(20.0, 12.0, identity, cov)) == "added"
    graph.add_odometry(61.0, planar_pose7(51.0, 0, 0))  # reaches the pending loop
    assert graph.counts.loops_added == 2 and not graph.pending
    graph.add_loop(loop(70.0, 12.0, identity, cov))
    graph.finish()
    assert graph.counts.skipped == {
        "loop: stamp before the odometry history": 1,
        "loop: stamp in an odometry gap": 1,
        "loop: covariance has NaN or infinite values": 1,
        "loop: covariance is not positive definite": 1,
        "loop: both loop stamps fall on the same graph node": 1,
        "loop: transform: pose has a zero quaternion": 1,
        "loop: stamp after the newest odometry": 1,
        "loop: no odometry yet": 1,
    }


def test_a_lone_loop_after_a_large_drift_needs_the_innovation_kernel():
    """One true loop, 16 m of travel, 1 m of drift: the loop's own covariance (1 cm) makes it an
    outlier for the plain kernel; widened by the graph's uncertainty it closes the lap."""
    stamps = 100.0 + np.arange(41) / 10.0
    s = stamps - 100.0
    corners = np.array([(0, 0), (4, 0), (4, 4), (0, 4), (0, 0)], float)
    k = np.minimum(s.astype(int), 3)
    xy = corners[k] + (corners[k + 1] - corners[k]) * (s - k)[:, None]
    truth = np.column_stack([xy, np.where(s >= 4.0, 0.0, k * math.pi / 2)])
    odometry = drives.drifting_odometry(truth, 10.0, 0, drives.OdometryNoise(0.02, 5.0, 0, 0))
    cov = np.diag([1e-4] * 3 + [1e-6] * 3)
    ends = {}
    for innovation in (False, True):
        graph = PoseGraph(PoseGraphConfig(node_spacing_m=0.5, innovation_kernel=innovation))
        for stamp, pose in zip(stamps, odometry, strict=True):
            graph.add_odometry(float(stamp), planar_pose7(*pose))
        graph.add_loop(make_factor(104.0, 100.0, gtsam.Pose3(), cov))
        graph.finish()
        ends[innovation] = float(np.hypot(*graph.optimised_poses()[-1, :2]))
    assert np.hypot(*odometry[-1, :2]) > 0.9
    assert ends[False] > 0.8 and ends[True] < 0.01, ends


def test_loops_waiting_for_odometry_are_bounded():
    graph = PoseGraph()
    graph.add_odometry(1.0, planar_pose7(0, 0, 0))
    for k in range(MAX_PENDING + 5):
        assert graph.add_loop(loop(10.0 + k, 1.0)) == "pending"
    assert len(graph.pending) == MAX_PENDING
    assert graph.counts.skipped == {"loop: waited too long for odometry": 5}
    assert graph.pending[0].query_stamp == 15.0  # the oldest went first


def test_config_is_validated():
    with pytest.raises(ConfigError, match="node_spacing_m=0.0 must be a positive number"):
        PoseGraph(PoseGraphConfig(node_spacing_m=0.0))
    with pytest.raises(ConfigError, match="loop_kernel='tukey' must be one of cauchy, huber, no"):
        PoseGraph(PoseGraphConfig(loop_kernel="tukey"))
    with pytest.raises(ConfigError, match="camera_to_base: pose has NaN"):
        PoseGraph(PoseGraphConfig(camera_to_base=(math.nan, 0, 0, 0, 0, 0, 1)))
