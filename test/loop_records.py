"""A posed, accepted `LoopRecord` for the tests of the messages and the pose graph (importable
from any test file: test/ is on the path, so each file still runs alone)."""

from __future__ import annotations

import math

import numpy as np

from pair_vpr_ros.loops.records import LoopRecord

COV = tuple(float(v) for v in np.diag([0.01, 0.02, 0.03, 1e-4, 2e-4, 3e-4]).ravel())


def posed_record(**over) -> LoopRecord:
    """Query 40 matched to keyframe 3 with a metric pose (88 inliers) and covariance `COV`;
    keyword arguments replace fields."""
    fields = dict(
        query_id=40, query_stamp=1700000012.25, query_frame_id="cam_q", match_id=3,
        match_stamp=1700000001.5, match_frame_id="cam_m", pair_score=2.0, global_similarity=0.9,
        rank_before=1, rank_after=1, accepted=True, pose_status="metric", pose_inliers=88,
        tx=0.5, ty=-0.1, tz=2.0, qx=0.0, qy=math.sin(0.2), qz=0.0, qw=math.cos(0.2),
        covariance=COV,
    )  # fmt: skip
    return LoopRecord(**{**fields, **over})
