"""Depth-noise model, robust keypoint depth, and PnP covariances that match their error under
a physically realistic noise model (pixel noise + sigma_z = a + b z^2): PoseLib's pose, the
covariance of `metric_pose`."""

from __future__ import annotations

import numpy as np
import pytest

from pair_vpr_ros.geometry import PoseConfig, camera_from_params
from pair_vpr_ros.geometry.camera import project
from pair_vpr_ros.geometry.depth_noise import (
    depth_sigma,
    point_covariances,
    point_sigmas,
    robust_depth_at,
    sigma_at,
)
from pair_vpr_ros.geometry.features import Features
from pair_vpr_ros.geometry.metric_pose import metric_fit
from pair_vpr_ros.geometry.rotations import exp_so3, log_so3

AB = (0.0012, 0.0019)
K = np.array([[520.0, 0.0, 320.0], [0.0, 520.0, 240.0], [0.0, 0.0, 1.0]])
CAM = camera_from_params(640, 480, 520.0, 520.0, 320.0, 240.0)


def test_depth_sigma_grows_with_the_square_of_the_depth():
    np.testing.assert_allclose(depth_sigma(np.array([1.0, 3.0, 5.0]), *AB),
                               [0.0031, 0.0183, 0.0487])  # fmt: skip


def test_robust_depth_is_the_window_median_and_none_at_edges_or_holes():
    depth = np.full((20, 20), 2.0, np.float32)
    depth[5, 5] = 2.2  # one noisy pixel: the median ignores it
    depth[:, 12:] = 6.0  # a depth edge between columns 11 and 12
    depth[15:, :6] = np.nan  # a hole
    depth[0:3, 0:3] = 0.0  # 16UC1 zeros: no reading
    px = np.array([[5, 5], [11, 8], [15, 8], [2, 17], [1, 1], [-3, 30], [4, 4]], np.float32)
    z = robust_depth_at(depth, px, *AB)
    assert z[0] == pytest.approx(2.0) and z[2] == pytest.approx(6.0)
    assert np.isnan(z[1])  # window spans 2 m and 6 m
    assert np.isnan(z[3])  # over half of the window is a hole
    assert np.isnan(z[4])  # 9 of 25 outside the image, 9 zeros: 7 of 25 readings
    assert z[6] == pytest.approx(2.0)  # one zero and one stray reading in the window
    assert np.isnan(z[5])  # clipped to the corner (19, 0): half the window is outside


def test_a_depths_own_sigma_is_used_where_it_is_a_positive_number():
    """Stereo depth's own sigma per keypoint; NaN (none), 0, negative or inf (a damaged or
    foreign record) fall back to the model a + b z^2, so no point gets a weight from them."""
    z = np.full(6, 3.0)
    own = np.array([0.02, np.nan, 0.0, -0.01, np.inf, 0.005])
    model = depth_sigma(z, *AB)
    np.testing.assert_allclose(point_sigmas(z, *AB, own), [0.02, *model[1:5], 0.005])
    np.testing.assert_allclose(point_sigmas(z, *AB), model)
    cov = point_covariances(np.array([[0.0, 0.0, 1.0]] * 6), z, 1.0, 500.0, *AB, own)
    np.testing.assert_allclose(np.sqrt(cov[:, 2, 2]), point_sigmas(z, *AB, own))


def test_sigma_at_a_keypoint_is_its_window_median_where_it_has_depth():
    sigma = np.full((20, 20), 0.01, np.float32)
    sigma[:, 10:] = 0.05
    sigma[8, 3] = 9.0  # one stray value: the median ignores it
    px = np.array([[3, 8], [15, 8], [3, 8]], np.float32)
    out = sigma_at(sigma, px, np.array([2.0, 2.0, np.nan], np.float32))
    np.testing.assert_allclose(out[:2], [0.01, 0.05])
    assert np.isnan(out[2])  # no depth there: no sigma either


def test_point_covariance_is_depth_noise_along_the_ray_and_pixel_noise_across():
    cov = point_covariances(np.array([[0.0, 0.0, 1.0]]), np.array([4.0]), 1.0, 500.0, *AB)
    np.testing.assert_allclose(np.diag(cov[0]), [(4 / 500) ** 2, (4 / 500) ** 2,
                                                 (0.0012 + 0.0019 * 16) ** 2])  # fmt: skip


def _trial(rng, depth_ab, sigma_px=0.7):
    """Random scene 1-6 m in front of the match camera, query camera 0.6 m and ~8 deg away;
    noisy depth (the model's sigma_z) and pixels -> chi-square of the error of PoseLib's pose
    under the bare covariance (`metric_pose.metric_fit`, no covariance_scale)."""
    n = 80
    px_m = rng.uniform([20, 20], [620, 460], (n, 2))
    z_true = rng.uniform(1.0, 6.0, n)
    rays = np.c_[(px_m - K[:2, 2]) / K[0, 0], np.ones(n)]
    r_true, t_true = exp_so3(rng.normal(0, 0.08, 3)), rng.normal(0, 0.35, 3)  # T_match_query
    x_q = (rays * z_true[:, None] - t_true) @ r_true
    px_q = project(K, x_q) + rng.normal(0, sigma_px, (n, 2))
    z = z_true + rng.normal(0, 1, n) * depth_sigma(z_true, *AB)
    code = np.zeros((n, 128), np.uint8)
    q = Features(px_q.astype(np.float32), code, "sift", None, CAM)
    m = Features(px_m.astype(np.float32), code, "sift", z.astype(np.float32), CAM)
    config = PoseConfig(ransac_px=4 * sigma_px, covariance_scale=1.0,
                        depth_sigma_a=depth_ab[0], depth_sigma_b=depth_ab[1])  # fmt: skip
    fit = metric_fit(q, m, np.c_[np.arange(n), np.arange(n)], "match", z, config)
    r, t, cov = fit.rotation, fit.translation, fit.covariance
    d = np.r_[t_true - t, log_so3(r_true @ r.T)]
    return float(d @ np.linalg.solve(cov, d))


def test_pnp_covariance_with_depth_noise_matches_the_error():
    """6 dof: a calibrated covariance gives a median chi-square of 5.35."""
    rng = np.random.default_rng(3)
    chi2 = [_trial(rng, AB) for _ in range(60)]
    assert 3.5 < np.median(chi2) < 8.0, np.median(chi2)


def test_pixel_noise_larger_than_assumed_is_estimated_from_the_residuals():
    """2 px of pixel noise: the a-posteriori sigma follows the residuals (floor 0.25 px)."""
    rng = np.random.default_rng(4)
    chi2 = [_trial(rng, AB, sigma_px=2.0) for _ in range(40)]
    assert 3.5 < np.median(chi2) < 8.0, np.median(chi2)
