"""Stereo depth for keyframes: StereoSGBM on rectified pairs rendered in the demo world (the
right camera 0.3 m to the right of the left one, same heading), metric loops from it."""

from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from pair_vpr_ros.demo import generate_world
from pair_vpr_ros.demo.camera import Camera
from pair_vpr_ros.demo.render import render_view
from pair_vpr_ros.demo.views import camera_model, pose_errors, render_keyframe, true_relative_pose
from pair_vpr_ros.geometry import extract_features, relative_pose
from pair_vpr_ros.geometry.keyframes import KeyframeGeometry
from pair_vpr_ros.geometry.stereo import (
    MAX_DISPARITY_SIGMA_PX,
    SUBPIXEL_SIGMA_PX,
    disparity_sigma,
    left_right_difference,
    stereo_baseline,
    stereo_depth,
    stereo_noise_b,
)
from pair_vpr_ros.loops.frames import PipelineCounts

CAM = Camera()
MODEL = camera_model(CAM)
BASELINE = 1.0


def right_view(world, i: int) -> np.ndarray:
    """The right camera of a rectified pair: BASELINE m along the left camera's x axis."""
    x, y, yaw = (float(v) for v in world.poses[i][:3])
    pose = np.array([x + BASELINE * math.sin(yaw), y - BASELINE * math.cos(yaw), yaw])
    return render_view(world.layout, pose, world.lighting_of(i), world.occluders_of(i), CAM,
                       (world.seed, i, 1))  # fmt: skip


@pytest.fixture(scope="module")
def world():
    return generate_world(5)


def info(p03: float, fx: float = 200.0) -> SimpleNamespace:
    return SimpleNamespace(p=[fx, 0, 160, p03, 0, fx, 120, 0, 0, 0, 1, 0])


def test_baseline_from_the_right_camera_info():
    assert stereo_baseline(info(-200.0 * 0.12)) == pytest.approx(0.12)
    assert stereo_noise_b(400.0, 0.1, 0.5) == pytest.approx(0.0125)


def test_stereo_depth_matches_the_rendered_depth(world):
    rgb, truth = render_keyframe(world, 40)
    depth, sigma = stereo_depth(rgb, right_view(world, 40), MODEL.fx, BASELINE)
    ok = np.isfinite(depth) & (truth > 0) & (truth < 20)
    assert ok.mean() > 0.25  # flat-shaded facades: little texture to match
    rel = np.abs(depth[ok] - truth[ok]) / truth[ok]
    assert np.median(rel) < 0.06, np.median(rel)
    # each depth's own std: z^2 sigma_d / (f B), sigma_d from the left image's texture and
    # the left-right difference (mostly 0 here)
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    texture = depth[ok] ** 2 * disparity_sigma(grey)[ok] / (MODEL.fx * BASELINE)
    assert np.all(sigma[ok] >= 0.999 * texture) and np.median(sigma[ok] / texture) < 1.01
    assert np.array_equal(np.isfinite(sigma), np.isfinite(depth))


def test_disparity_sigma_is_small_on_texture_and_large_where_flat():
    """A block with horizontal gradients fixes the disparity to about its sub-pixel error; a
    flat block, or one striped along the rows (no gradient across them), does not."""
    rng = np.random.default_rng(0)
    img = np.full((60, 90), 128, np.uint8)
    img[:, :30] = rng.integers(0, 256, (60, 30))  # textured
    img[:, 60:] = np.where(np.arange(60)[:, None] % 4 < 2, 60, 200)  # stripes along the rows
    s = disparity_sigma(img)
    assert np.allclose(s[10:50, 5:25], SUBPIXEL_SIGMA_PX, atol=0.05)
    assert np.all(s[10:50, 35:55] == np.float32(MAX_DISPARITY_SIGMA_PX))  # flat
    assert np.all(s[10:50, 65:85] == np.float32(MAX_DISPARITY_SIGMA_PX))  # row stripes
    weak = (img[:, :30] // 64 + 120).astype(np.uint8)
    s_weak = disparity_sigma(weak)[10:50, 5:25]  # the same texture at 1/64 contrast
    assert np.median(s_weak) > 1.5 * np.median(s[10:50, 5:25])


def test_left_right_difference_finds_a_match_the_right_image_does_not_confirm():
    left = np.full((4, 40), 5.0, np.float32)  # every left pixel x matches right x - 5 ...
    right = np.full((4, 40), 5.0, np.float32)
    left[1, 20] = 12.0  # ... but this one claims x - 12, where the right image says 5
    right[2, 15] = 0.0  # and here the right image has no match: no verdict
    lr = left_right_difference(left, right)
    assert lr[1, 20] == 7.0 and np.isnan(lr[2, 20]) and lr[0, 20] == 0.0
    left[3, 30] = -1.0  # no left disparity
    assert np.isnan(left_right_difference(left, right)[3, 30])


def test_stereo_keyframes_give_a_metric_loop(world):
    q, m = next((q, m) for q, m in world.revisit_pairs() if q % (world.num_frames // 3) == 60)
    counts = PipelineCounts()
    geo = KeyframeGeometry(None, counts)
    fq = geo.extract(render_keyframe(world, q)[0], None, MODEL, right_view(world, q), BASELINE)
    fm = geo.extract(render_keyframe(world, m)[0], None, MODEL, right_view(world, m), BASELINE)
    assert (counts.stereo_depth, counts.stereo_invalid) == (2, 0)
    has = np.isfinite(fm.depth)  # each stereo depth with its own std
    assert has.sum() > 30 and np.all(fm.depth_sigma[has] > 0)
    pose = relative_pose(fq, fm)
    assert pose.status == "metric", pose.reason
    truth = true_relative_pose(world.poses[m], world.poses[q], CAM)
    rot, trans, _ = pose_errors(pose.matrix(), truth)
    assert rot < 0.5 and trans < 0.3, (rot, trans)


def test_keyframe_with_depth_keeps_it_and_skips_stereo(world):
    rgb, depth = render_keyframe(world, 40)
    counts = PipelineCounts()
    f = KeyframeGeometry(None, counts).extract(rgb, depth, MODEL, right_view(world, 40), 0.3)
    ref = extract_features(rgb, depth=depth, camera=MODEL)
    np.testing.assert_array_equal(f.depth, ref.depth)
    assert (counts.stereo_depth, counts.stereo_invalid) == (0, 0)
