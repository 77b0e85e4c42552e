"""Monocular loops take their scale from a short odometry baseline next to the match keyframe
(rendered demo views with known poses), and stay scale-free, saying why, when there is none."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pair_vpr_ros.demo import generate_world
from pair_vpr_ros.demo.camera import Camera
from pair_vpr_ros.demo.views import camera_model, pose_errors, render_keyframe, true_relative_pose
from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry import PoseConfig, extract_features, relative_pose
from pair_vpr_ros.geometry.covariance import SCALE_FREE_VARIANCE
from pair_vpr_ros.geometry.odometry_scale import Neighbour, pick_neighbours, scaled_pose

CAM = Camera()
MODEL = camera_model(CAM)
NO_DEPTH = "no depth image (monocular): the translation is a direction only; "


def odom(pose: np.ndarray, scale: float = 1.0) -> tuple:
    """Demo camera pose (x, y, yaw) -> an odometry pose (x, y, z, qx, qy, qz, qw), positions
    multiplied by `scale` (an odometry with a scale error)."""
    x, y, yaw = (float(v) for v in pose)
    return (x * scale, y * scale, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


@pytest.fixture(scope="module")
def scene():
    """A revisit (query lap 1, match lap 0) and the match's two neighbouring frames."""
    world = generate_world(5)
    q, m = next((q, m) for q, m in world.revisit_pairs() if q % (world.num_frames // 3) == 30)
    feats = {i: extract_features(render_keyframe(world, i)[0], camera=MODEL)
             for i in (q, m - 1, m, m + 1)}  # fmt: skip
    truth = true_relative_pose(world.poses[m], world.poses[q], CAM)
    return world, q, m, feats, truth


def neighbours(scene, scale: float = 1.0, config: PoseConfig | None = None) -> list[Neighbour]:
    world, _, m, feats, _ = scene
    near = [(i, float(i), odom(world.poses[i], scale)) for i in (m - 1, m + 1)]
    return pick_neighbours(float(m), odom(world.poses[m], scale), near, feats.get,
                           config or PoseConfig())  # fmt: skip


def test_the_scale_comes_from_the_odometry_next_to_the_match(scene):
    _, q, m, feats, truth = scene
    pose = relative_pose(feats[q], feats[m], neighbours=neighbours(scene))
    assert pose.status == "metric-odometry"
    assert pose.reason.startswith(
        tuple(
            f"scale from the odometry to keyframes {a}, {b} (36 points)"
            for a, b in ((m - 1, m + 1), (m + 1, m - 1))
        )
    )
    assert np.linalg.norm(truth[:3, 3]) > 1.0
    rot, trans, direction = pose_errors(pose.matrix(), truth)
    assert rot < 2.0 and direction < 10.0 and trans < 0.3 * np.linalg.norm(truth[:3, 3])
    cov = pose.covariance
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov)[0] > 0
    length = np.linalg.norm(pose.translation)
    t_hat = pose.translation / length
    along = math.sqrt(t_hat @ cov[:3, :3] @ t_hat)  # the length's std, m
    assert 0.03 * length <= along < 0.5
    assert abs(length - np.linalg.norm(truth[:3, 3])) < 3 * along
    assert pose.record_fields()["pose_status"] == "metric-odometry"


def test_an_odometry_scale_error_moves_the_length_by_the_same_factor(scene):
    _, q, m, feats, _ = scene
    loose = PoseConfig(max_translation_sigma_m=1.0)  # the longer length's std is over 0.5 m
    exact = relative_pose(feats[q], feats[m], loose, neighbours=neighbours(scene))
    scaled = relative_pose(feats[q], feats[m], loose, neighbours=neighbours(scene, scale=1.1))
    assert scaled.status == "metric-odometry"
    ratio = np.linalg.norm(scaled.translation) / np.linalg.norm(exact.translation)
    assert ratio == pytest.approx(1.1, rel=1e-6)
    np.testing.assert_allclose(scaled.rotation, exact.rotation)


def test_without_a_baseline_the_pose_stays_scale_free_and_says_why(scene):
    world, q, m, feats, _ = scene
    no_pose = pick_neighbours(float(m), None, [(m + 1, m + 1.0, odom(world.poses[m + 1]))],
                              feats.get, PoseConfig())  # fmt: skip
    few = PoseConfig(scale_min_points=10_000)
    cases = [
        (
            (),
            PoseConfig(),
            "no map keyframe next to the match keyframe has an odometry baseline "
            "(both poses known, stamps within 10 s, at least 0.2 m apart, turned at most 10 deg)",
        ),
        (no_pose, PoseConfig(), "no map keyframe next to"),
        (neighbours(scene), few, "too few loop inliers with a triangulated point (36 < 10000)"),
    ]
    for near, config, reason in cases:
        pose = relative_pose(feats[q], feats[m], config, neighbours=near)
        # (this view's upper and lower rows disagree by 2.6 deg: its rotation std is widened)
        assert pose.status == "scale-free" and pose.reason.startswith(NO_DEPTH), pose.reason
        assert ("; no scale from odometry: " + reason) in pose.reason
        assert np.linalg.norm(pose.translation) == pytest.approx(1.0)
        np.testing.assert_array_equal(pose.covariance[:3, :3], np.eye(3) * SCALE_FREE_VARIANCE)
    off = relative_pose(feats[q], feats[m], PoseConfig(odometry_scale=False), neighbours(scene))
    assert off.status == "scale-free" and off.reason.endswith(
        "switched off (odometry_scale false)"
    )


def test_odometry_that_disagrees_with_the_images_is_not_used(scene):
    _, q, m, feats, _ = scene
    lying = [Neighbour(n.id, n.baseline_m, n.turn_deg + 2.5, n.load) for n in neighbours(scene)]
    pose = relative_pose(feats[q], feats[m], neighbours=lying)
    assert pose.status == "scale-free"
    assert "odometry and images disagree" in pose.reason


def test_neighbours_are_picked_by_time_baseline_and_turn():
    config = PoseConfig()
    here = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    half = math.radians(12) / 2
    turned = (1.0, 0.0, 0.0, 0.0, 0.0, math.sin(half), math.cos(half))
    near = [
        (1, 1.0, (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)),  # fit
        (2, 2.0, (2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)),  # fit, longer
        (3, 30.0, (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)),  # too long ago
        (4, 1.0, (0.05, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)),  # baseline too short
        (5, 1.0, turned),  # turned too much (the camera's lever arm)
        (6, 1.0, None),  # no odometry
    ]
    got = pick_neighbours(0.0, here, near, lambda i: None, config)
    assert [(n.id, n.baseline_m) for n in got] == [(2, 2.0), (1, 1.0)]
    assert pick_neighbours(0.0, None, near, lambda i: None, config) == []


@pytest.mark.parametrize(
    ("name", "value", "match"),
    [
        ("scale_min_baseline_m", 0.0, "pose scale_min_baseline_m=0.0 must be > 0"),
        ("scale_sigma_floor", -1.0, "pose scale_sigma_floor=-1.0 must be > 0"),
        ("scale_max_turn_deg", float("nan"), "pose scale_max_turn_deg=nan must be > 0"),
        ("scale_min_points", 0, "pose scale_min_points=0 must be >= 1"),
        ("scale_tries", 0, "pose scale_tries=0 must be >= 1"),
    ],
)
def test_scale_settings_are_checked(name, value, match):
    with pytest.raises(ConfigError, match=match):
        PoseConfig(**{name: value})


def test_a_length_undefined_within_the_pose_std_is_a_reason_not_a_crash():
    """Demo seed 8, query 211 on match 51: the old centre / rim check widened the monocular
    pose's covariance (x3.1), and a pose one std away left no triangulated point in front of
    the cameras: NaN lengths and a LinAlgError, then a reason. PoseLib's pose with its own
    covariance has a length; a covariance that wide is a reason, never a crash."""
    world = generate_world(8)
    q, m = 211, 51
    feats = {i: extract_features(render_keyframe(world, i)[0], camera=MODEL)
             for i in (q, m - 2, m - 1, m, m + 1, m + 2)}  # fmt: skip
    near = [(i, float(i), odom(world.poses[i])) for i in (m - 2, m - 1, m + 1, m + 2)]
    found = pick_neighbours(float(m), odom(world.poses[m]), near, feats.get, PoseConfig())
    pose = relative_pose(feats[q], feats[m], neighbours=found)
    assert (pose.status, pose.reason) == (
        "metric-odometry",
        "scale from the odometry to keyframes 49, 53 (21 points)",
    )
    pairs = pose.inlier_pairs
    fit = (pose.rotation, pose.translation / np.linalg.norm(pose.translation))
    wide = np.eye(5) * 0.09  # 17 deg on each axis
    assert scaled_pose(feats[q], feats[m], pairs, (*fit, wide), PoseConfig(), found) == (
        "too uncertain (std 9.45 m)"
    )
