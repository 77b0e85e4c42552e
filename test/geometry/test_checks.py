"""The model checks (geometry/checks.py) on a monocular pose: the upper and lower rows of a
rolling-shutter image turned while they were read out; PoseLib refines each half."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pair_vpr_ros.geometry import PoseConfig, camera_from_params
from pair_vpr_ros.geometry.checks import split_keys, split_variances
from pair_vpr_ros.geometry.epipolar import essential_fit, essential_refit
from pair_vpr_ros.geometry.features import Features
from pair_vpr_ros.geometry.rotations import exp_so3

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
CAM = camera_from_params(640, 480, 500.0, 500.0, 320.0, 240.0)


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


def _variance(px_q, px_m, rows_only: bool = True) -> tuple[float, str]:
    code = np.zeros((len(px_q), 128), np.uint8)
    q, m = (Features(p.astype(np.float32), code, "sift", None, CAM) for p in (px_q, px_m))
    fit = essential_fit(q, m, np.c_[np.arange(len(px_q)), np.arange(len(px_q))], PoseConfig())
    keys = split_keys(*fit.keypoints, ((320.0, 240.0), (320.0, 240.0)))
    if rows_only:
        keys = {"rows": keys["rows"]}
    return split_variances(keys, essential_refit(fit, (CAM, CAM), 0.25), fit.covariance[2:, 2:])


def test_a_global_shutter_adds_next_to_nothing():
    """The halves differ by noise only (0.3 px): each split is within its halves' own
    covariances but for the 5 % that its 95 % point lets through, and those add little."""
    found = [_variance(*_two_views(turn_rate=0.0, seed=seed), rows_only=False)
             for seed in range(10)]  # fmt: skip
    assert sum(words.count("disagree") for _, words in found) <= 3  # of 30 splits
    assert max(math.degrees(math.sqrt(v)) for v, _ in found) < 0.05


@pytest.mark.parametrize("rate_deg", [40.0, 80.0])
def test_a_rolling_shutter_turning_adds_what_the_rows_disagree_by(rate_deg):
    """Turning 40-80 deg/s over a 30 ms readout bends the query image by 1.2-2.4 deg from its
    top to its bottom row: the halves' rotations differ by a sizeable part of that."""
    variance, words = _variance(*_two_views(turn_rate=math.radians(rate_deg)))
    assert words.startswith("the upper and lower rows (rolling shutter?) disagree by ")
    angle = float(words.split(" by ")[1].split(" deg")[0])
    assert 0.5 * rate_deg * 0.03 < angle < rate_deg * 0.03
    assert variance == pytest.approx(math.radians(angle / 2) ** 2, rel=0.02)


def test_too_few_points_in_a_half_gives_nothing():
    keys = {"rows": np.arange(15.0)}

    def refit(sel):
        raise AssertionError("no half of 7 points is refitted")

    assert split_variances(keys, refit, np.eye(3)) == (0.0, "")
