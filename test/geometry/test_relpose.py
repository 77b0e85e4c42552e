"""Relative pose on rendered demo views with known poses, and every bad input's reason."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from pair_vpr_ros.demo import generate_world
from pair_vpr_ros.demo.camera import Camera
from pair_vpr_ros.demo.views import camera_model, pose_errors, render_keyframe, true_relative_pose
from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry import PoseConfig, camera_from_params, extract_features, relative_pose
from pair_vpr_ros.geometry.camera import project
from pair_vpr_ros.geometry.covariance import SCALE_FREE_VARIANCE
from pair_vpr_ros.geometry.epipolar import essential_fit
from pair_vpr_ros.geometry.features import Features, empty_features
from pair_vpr_ros.geometry.rotations import exp_so3

CAM = Camera()
MODEL = camera_model(CAM)


@pytest.fixture(scope="module")
def views():
    """A revisit (query on lap 1, match on lap 0: other lighting, 1-3 m and 10-25 deg away) and
    the true T_match_query."""
    world = generate_world(5)
    q, m = next((q, m) for q, m in world.revisit_pairs() if q % (world.num_frames // 3) == 60)
    (rq, dq), (rm, dm) = render_keyframe(world, q), render_keyframe(world, m)
    truth = true_relative_pose(world.poses[m], world.poses[q], CAM)
    return rq, dq, rm, dm, truth


def test_metric_pose_from_the_match_depth(views):
    rq, _, rm, dm, truth = views
    assert (
        np.linalg.norm(truth[:3, 3]) > 1.0
        and math.degrees(math.acos((np.trace(truth[:3, :3]) - 1) / 2)) > 5
    )  # a real viewpoint change
    pose = relative_pose(extract_features(rq, camera=MODEL),
                         extract_features(rm, depth=dm, camera=MODEL))  # fmt: skip
    assert (pose.status, pose.reason) == ("metric", "")
    rot, trans, _ = pose_errors(pose.matrix(), truth)
    assert rot < 0.5 and trans < 0.15 and pose.inliers >= 30
    cov = pose.covariance
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov)[0] > 0
    assert np.sqrt(cov[0, 0]) < 0.3 and np.degrees(np.sqrt(cov[3, 3])) < 1.0
    fields = pose.record_fields()
    assert fields["pose_status"] == "metric" and len(fields["covariance"]) == 36
    assert math.isclose(sum(fields[k] ** 2 for k in ("qx", "qy", "qz", "qw")), 1.0)


def test_metric_pose_from_the_query_depth_when_the_match_has_none(views):
    rq, dq, rm, _, truth = views
    pose = relative_pose(extract_features(rq, depth=dq, camera=MODEL),
                         extract_features(rm, camera=MODEL))  # fmt: skip
    assert pose.status == "metric"
    rot, trans, _ = pose_errors(pose.matrix(), truth)
    assert rot < 0.5 and trans < 0.15


def test_scale_free_pose_without_depth(views):
    rq, _, rm, _, truth = views
    pose = relative_pose(extract_features(rq, camera=MODEL), extract_features(rm, camera=MODEL))
    assert pose.status == "scale-free"
    # (this view's centre and rim rotations differ by 1.2 deg: its covariance is scaled x2.1)
    assert pose.reason.startswith("no depth image (monocular): the translation is a direction")
    assert pose.reason.endswith(
        "; no scale from odometry: no map keyframe next to the match keyframe has an odometry "
        "baseline (both poses known, stamps within 10 s, at least 0.2 m apart, turned at most "
        "10 deg)"
    )
    rot, _, direction = pose_errors(pose.matrix(), truth)
    assert rot < 2.0 and direction < 10.0
    assert np.linalg.norm(pose.translation) == pytest.approx(1.0)
    np.testing.assert_array_equal(pose.covariance[:3, :3], np.eye(3) * SCALE_FREE_VARIANCE)
    assert 0 < pose.covariance[3, 3] < 1e-3 and not pose.covariance[:3, 3:].any()


@pytest.mark.parametrize("bad", ["zeros", "nan"])
def test_depth_without_values_gives_a_scale_free_pose_with_the_reason(views, bad):
    rq, _, rm, dm, _ = views
    empty = np.zeros_like(dm) if bad == "zeros" else np.full_like(dm, np.nan)
    pose = relative_pose(extract_features(rq, camera=MODEL),
                         extract_features(rm, depth=empty, camera=MODEL))  # fmt: skip
    assert pose.status == "scale-free"
    assert pose.reason.startswith("no depth at the keypoints (0 of ")


def test_missing_inputs_give_reasons_not_poses(views):
    rq, _, rm, dm, _ = views
    q = extract_features(rq, camera=MODEL)
    m = extract_features(rm, depth=dm, camera=MODEL)
    cases = [
        (q, None, "match keyframe has no features (kept only for keyframes added since"),
        (None, m, "query keyframe has no features"),
        (replace(q, camera=None), m, "no intrinsics for the query keyframe (no camera_info"),
        (q, replace(m, camera=None), "no intrinsics for the match keyframe"),
        (q, extract_features(rm, "orb", camera=MODEL), "feature kinds differ (query sift, match"),
        (q, replace(empty_features(), camera=MODEL), "the match image has no keypoints"),
        (
            q,
            replace(m, keypoints=m.keypoints[:9], descriptors=m.descriptors[:9], depth=None),
            "too few feature matches (",
        ),
    ]
    for a, b, reason in cases:
        pose = relative_pose(a, b)
        assert pose.status == "" and pose.reason.startswith(reason), pose.reason
        assert pose.rotation is None and pose.record_fields() == dict(
            pose_status="", pose_reason=pose.reason, pose_inliers=pose.inliers
        )


def test_unrelated_places_get_no_metric_pose():
    world = generate_world(6)
    (ra, _), (rb, db) = render_keyframe(world, 10), render_keyframe(world, 90)
    pose = relative_pose(extract_features(ra, camera=MODEL),
                         extract_features(rb, depth=db, camera=MODEL))  # fmt: skip
    assert pose.status == "" and pose.reason.startswith("too few"), pose.reason


def test_orb_features_also_give_a_metric_pose(views):
    rq, _, rm, dm, truth = views
    pose = relative_pose(extract_features(rq, "orb", camera=MODEL),
                         extract_features(rm, "orb", depth=dm, camera=MODEL))  # fmt: skip
    assert pose.status == "metric"
    rot, trans, _ = pose_errors(pose.matrix(), truth)
    assert rot < 1.0 and trans < 0.3


def test_pose_config_checks_its_values():
    with pytest.raises(ConfigError, match="pose ratio=1.5 must be in"):
        PoseConfig(ratio=1.5)
    with pytest.raises(ConfigError, match="pose ransac_px=0 must be > 0"):
        PoseConfig(ransac_px=0)
    with pytest.raises(ConfigError, match="min_inliers must be >= 6"):
        PoseConfig(min_inliers=3)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("depth_sigma_a", -0.1, "pose depth_sigma_a=-0.1 must be >= 0"),
        ("depth_sigma_b", 0.0, "pose depth_sigma_b=0.0 must be > 0"),
        ("max_depth_m", float("nan"), "pose max_depth_m=nan must be >= 0"),
        ("depth_agreement_sigmas", -1.0, "pose depth_agreement_sigmas=-1.0 must be > 0"),
        ("floor_rotation_deg", -0.2, "pose floor_rotation_deg=-0.2 must be >= 0"),
        ("systematic_px", -1.0, "pose systematic_px=-1.0 must be >= 0"),
        ("systematic_px", float("nan"), "pose systematic_px=nan must be >= 0"),
        ("floor_px", -0.1, "pose floor_px=-0.1 must be >= 0"),
        ("depth_registration_px", -1.0, "pose depth_registration_px=-1.0 must be >= 0"),
    ],
)
def test_depth_noise_and_floor_settings_are_checked(field, value, message):
    with pytest.raises(ConfigError) as err:
        PoseConfig(**{field: value})
    assert str(err.value) == message


def test_systematic_terms_are_added_to_every_pose(views):
    rq, _, rm, dm, _ = views
    q, m = extract_features(rq, camera=MODEL), extract_features(rm, depth=dm, camera=MODEL)
    zero = dict(floor_translation_m=0.0, floor_translation_rel=0.0)
    bare = relative_pose(q, m, PoseConfig(**zero))
    added = relative_pose(q, m, PoseConfig(systematic_px=1.8))
    diff = added.covariance - bare.covariance
    length = np.linalg.norm(bare.translation)
    np.testing.assert_allclose(np.diag(diff), [(0.005 + 0.01 * length) ** 2] * 3
                               + [(1.8 / MODEL.fx) ** 2] * 3)  # fmt: skip
    # pose_floor_rotation_deg is a lower bound: 1.8 px is 0.64 deg on this 160 px focal length
    at_least = relative_pose(q, m, PoseConfig(**zero, floor_rotation_deg=1.0))
    np.testing.assert_allclose(np.diag(at_least.covariance - bare.covariance)[3:],
                               [math.radians(1.0) ** 2] * 3, rtol=1e-6)  # fmt: skip


def _synthetic_pair(f: float, size: tuple[int, int]):
    """The same 3-D scene seen by two poses of a camera with focal length f (px) and image
    size -> (query features, match features with exact depth), no pixel noise."""
    rng = np.random.default_rng(3)
    pts = np.c_[rng.uniform(-2, 2, (80, 2)), rng.uniform(4, 8, 80)]  # match frame
    r, t = exp_so3(np.radians([0.0, 8.0, 0.0])), np.array([0.4, 0.0, 0.1])
    cam = camera_from_params(*size, f, f, size[0] / 2, size[1] / 2)
    code = rng.integers(0, 256, (80, 128)).astype(np.uint8)
    px_m = project(cam.k, pts).astype(np.float32)
    px_q = project(cam.k, (pts - t) @ r).astype(np.float32)  # X_q = R^T (X_m - t)
    return Features(px_q, code, "sift", None, cam), Features(px_m, code, "sift", pts[:, 2], cam)


def test_systematic_rotation_is_pixels_at_each_cameras_focal_length():
    """A camera with twice the focal length (twice the pixels over the same view) gets half the
    systematic rotation: pose_systematic_px pixels' angle, not one angle for every camera."""
    added = []
    for f, size in ((400.0, (640, 480)), (800.0, (1280, 960))):
        q, m = _synthetic_pair(f, size)
        bare = relative_pose(q, m, PoseConfig())
        with_term = relative_pose(q, m, PoseConfig(systematic_px=1.8))
        assert (bare.status, with_term.status) == ("metric", "metric")
        added.append(np.diag(with_term.covariance - bare.covariance)[3:])
        np.testing.assert_allclose(added[-1], [(1.8 / f) ** 2] * 3, rtol=1e-6)
    np.testing.assert_allclose(np.sqrt(added[0] / added[1]), 2.0, rtol=1e-6)


def test_the_pixel_floor_is_a_lower_bound_only():
    """Noise-free pixels fit to ~0: the floor, not the residuals, sets sigma, and the
    covariance grows with its square; pixel noise larger than the floor sets it instead."""
    q, m = _synthetic_pair(400.0, (640, 480))
    m.depth = None
    pairs = np.c_[np.arange(len(q)), np.arange(len(q))]
    fits = [essential_fit(q, m, pairs, PoseConfig(floor_px=f)) for f in (0.25, 0.5)]
    np.testing.assert_allclose(fits[1].covariance, 4 * fits[0].covariance, rtol=1e-6)
    noisy = replace(q, keypoints=q.keypoints + np.random.default_rng(0).normal(0, 0.6, (80, 2))
                    .astype(np.float32))  # fmt: skip
    loose = [essential_fit(noisy, m, pairs, PoseConfig(floor_px=f)) for f in (0.0, 0.25)]
    np.testing.assert_allclose(loose[1].covariance, loose[0].covariance)
