"""A synthetic drive for pose-graph tests: laps of a rectangle, true and drifting odometry."""

from __future__ import annotations

import numpy as np

from pair_vpr_ros.demo.odometry import OdometryNoise, drifting_odometry

__all__ = ["CAMERA", "RATE", "OdometryNoise", "drifting_odometry", "drive", "rectangle_drive"]
from pair_vpr_ros.posegraph.transforms import planar_pose7

RATE = 10.0
CAMERA = (0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5)  # optical camera 1.6 m above the base


def rectangle_drive(laps: int = 3, width: float = 40.0, height: float = 30.0) -> np.ndarray:
    """Planar poses [N, 3] of `laps` laps around a rectangle at 8 m/s, 10 Hz."""
    corners = np.array([(0, 0), (width, 0), (width, height), (0, height), (0, 0)], float)
    seg = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    s = np.arange(0.0, laps * seg.sum(), 0.8) % seg.sum()
    edges = np.concatenate([[0.0], np.cumsum(seg)])
    x, y = np.interp(s, edges, corners[:, 0]), np.interp(s, edges, corners[:, 1])
    k = np.minimum(np.searchsorted(edges, s, side="right") - 1, 3)
    d = np.diff(corners, axis=0)[k]
    return np.stack([x, y, np.arctan2(d[:, 1], d[:, 0])], axis=1)


def drive(laps: int = 3, seed: int = 1):
    """-> stamps [N], true poses [N, 7], drifting odometry [N, 7], loop pairs [(query, match)]
    (every 3rd frame after the first lap, matched 3 frames (2.4 m) behind its first visit)."""
    truth = rectangle_drive(laps)
    odometry = drifting_odometry(truth, RATE, seed=seed, noise=OdometryNoise(0.01, 0.5))
    stamps = 100.0 + np.arange(len(truth)) / RATE
    gt7 = np.array([planar_pose7(*p) for p in truth])
    od7 = np.array([planar_pose7(*p) for p in odometry])
    lap = len(truth) // laps
    pairs = [(stamps[i], stamps[i % lap + 3]) for i in range(lap, len(truth) - 3, 3)]
    return stamps, gt7, od7, pairs
