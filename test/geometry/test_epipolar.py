"""The monocular pose's model checks (geometry/epipolar.py): the upper and lower rows of a
rolling-shutter image turned while they were read out."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from pair_vpr_ros.geometry.epipolar import essential_pose, row_split_variance
from pair_vpr_ros.geometry.rotations import exp_so3

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def _two_views(turn_rate: float, readout_s: float = 0.03, seed: int = 0):
    """400 points 2-6 m ahead seen by a match camera (global shutter) and a query camera 0.3 m
    to the side and 5 deg turned, whose row v is taken at v / 480 * readout_s while it turns
    about its y axis at turn_rate rad/s -> (ideal px_q [N, 2], px_m [N, 2])."""
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-3, 3, (400, 2)), rng.uniform(2, 6, 400)]  # match camera frame
    r_qm, t_qm = exp_so3(np.radians([0.0, 5.0, 0.0])), np.array([0.3, 0.0, 0.0])
    px_m = pts @ K.T
    px_m = px_m[:, :2] / px_m[:, 2:]
    px_q = np.empty_like(px_m)
    for i, x in enumerate(pts):
        v = 240.0
        for _ in range(3):  # the row a point lands on decides when it was seen
            r = exp_so3(np.array([0.0, turn_rate * v / 480 * readout_s, 0.0])) @ r_qm
            p = K @ (r @ x + t_qm)
            px_q[i], v = p[:2] / p[2], p[1] / p[2]
    noise = np.random.default_rng(seed + 1).normal(0, 0.3, (2, len(pts), 2))
    return px_q + noise[0], px_m + noise[1]


def _variance(px_q, px_m) -> tuple[float, float]:
    cv2.setRNGSeed(0)
    r, t, idx = essential_pose(px_q, px_m, K, 1.0, 15)
    return row_split_variance(px_q[idx], px_m[idx], K, (r, t), 0.5)


def test_a_global_shutter_adds_nothing():
    """The halves differ by noise only (0.3 px): within their own covariances."""
    variance, angle = _variance(*_two_views(turn_rate=0.0))
    assert variance == 0.0
    assert 0.0 < angle < 0.05


@pytest.mark.parametrize("rate_deg", [40.0, 80.0])
def test_a_rolling_shutter_turning_adds_what_the_rows_disagree_by(rate_deg):
    """Turning 40-80 deg/s over a 30 ms readout bends the query image by 1.2-2.4 deg from its
    top to its bottom row: the halves' rotations differ by a sizeable part of that."""
    variance, angle = _variance(*_two_views(turn_rate=math.radians(rate_deg)))
    assert 0.5 * rate_deg * 0.03 < angle < rate_deg * 0.03
    assert variance == pytest.approx(math.radians(angle / 2) ** 2)


def test_too_few_points_in_a_half_gives_nothing():
    px_q, px_m = _two_views(turn_rate=1.0)
    pose = (np.eye(3), np.array([1.0, 0, 0]))
    assert row_split_variance(px_q[:15], px_m[:15], K, pose, 0.5) == (0.0, 0.0)
