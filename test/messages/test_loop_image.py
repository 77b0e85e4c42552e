"""The loop image: query | match at one height, the inlier matches drawn where the points are,
the decision written above, a grey panel for a side without an image, the Image fields."""

from __future__ import annotations

import math

import numpy as np
from bag_fixtures import textured

from pair_vpr_ros.images.thumbnails import Thumbnail
from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.messages.loop_image import (
    decision_lines,
    draw_loop,
    image_fields,
    pose_sigmas,
)


def record(**fields) -> LoopRecord:
    base = LoopRecord(12, 40.0, "cam", 3, 5.0, "cam", 2.5, 0.875, 2, 1, inliers=40, accepted=True)
    for name, value in fields.items():
        setattr(base, name, value)
    return base


POSED = dict(
    pose_status="metric", tx=0.3, ty=0.0, tz=0.4, qx=0.0, qy=0.0, qz=0.0, qw=1.0,
    covariance=tuple(np.diag([0.01**2, 0.02**2, 0.01**2, 1e-4, 4e-4, 1e-4]).ravel()),
)  # fmt: skip


def test_decision_lines_say_scores_inliers_pose_or_reason():
    first, second = decision_lines(record(**POSED))
    assert first == "LOOP 12 -> 3  pair 2.50  sim 0.875  rank 2->1"
    sigma_deg = math.degrees(0.02)
    assert second == f"40 inliers, pose metric |t| 0.50 m, sigma 0.020 m {sigma_deg:.2f} deg"
    assert pose_sigmas(record(**POSED)) == (0.02, sigma_deg)
    rejected = record(accepted=False, reason="score below threshold", pair_score=math.nan,
                      inliers=-1)  # fmt: skip
    assert decision_lines(rejected) == (
        "REJECTED 12 -> 3  pair not scored  sim 0.875  rank 2->1",
        "score below threshold (not verified)",
    )
    unposed = record(pose_reason="too few PnP inliers (4 < 6)")
    assert decision_lines(unposed)[1] == "40 inliers, no pose: too few PnP inliers (4 < 6)"


def test_both_images_at_one_height_with_the_matches_drawn():
    query = Thumbnail(textured(1), 1.0)  # 160 x 120, as captured
    match = Thumbnail(textured(2)[::2, ::2].copy(), 0.5)  # kept at half size
    points = np.array([[40.0, 30.0, 100.0, 60.0]], np.float32)  # original pixels of both
    image = draw_loop(record(), query, match, points, height=240)
    assert image.shape == (42 + 240, 320 + 4 + 320, 3)
    assert image[5, 5].tolist() == [40, 120, 40]  # accepted: green banner (BGR)
    colour = [80, 220, 80]  # the first match's colour, on both of its ends
    assert image[42 + 60, 80].tolist() == colour  # (40, 30) x 2 in the query panel
    assert image[42 + 120, 324 + 200].tolist() == colour  # (100, 60) x 2 in the match panel
    rejected = draw_loop(record(accepted=False, reason="x"), query, None, points, height=120)
    assert rejected[5, 5].tolist() == [40, 40, 150]  # red banner
    grey = rejected[42 + 5 : 42 + 40, 164 + 5 : 164 + 150]  # the missing match: a grey panel
    assert rejected.shape == (42 + 120, 160 + 4 + 160, 3) and (grey == 90).mean() > 0.9


def test_image_fields():
    bgr = np.zeros((5, 7, 3), np.uint8)
    fields = image_fields(bgr)
    assert (fields["height"], fields["width"], fields["encoding"], fields["step"]) == (
        5, 7, "bgr8", 21,
    )  # fmt: skip
    assert fields["data"].shape == (105,) and fields["is_bigendian"] == 0
