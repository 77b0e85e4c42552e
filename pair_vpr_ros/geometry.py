"""Optional geometric verification of a loop candidate with OpenCV.

ORB keypoints on each keyframe, brute-force Hamming matching with Lowe's ratio test, then a
fundamental-matrix RANSAC; the inlier count (and inliers / ratio-test matches) decide. Off by
default: the pair classifier already sees both images, and RANSAC costs ~10 ms per candidate.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Features:
    keypoints: np.ndarray  # [M, 2] float32 pixel coordinates
    descriptors: np.ndarray  # [M, 32] uint8 ORB descriptors

    @property
    def nbytes(self) -> int:
        return self.keypoints.nbytes + self.descriptors.nbytes


def extract_features(rgb: np.ndarray, max_features: int = 1000, max_side: int = 640) -> Features:
    """RGB uint8 [H,W,3] -> ORB features, on a copy downscaled so its longer side <= max_side."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    scale = min(1.0, max_side / max(grey.shape))
    if scale < 1.0:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    orb = cv2.ORB_create(nfeatures=max_features)
    keypoints, descriptors = orb.detectAndCompute(grey, None)
    if descriptors is None:
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8))
    points = np.array([kp.pt for kp in keypoints], np.float32) / scale
    return Features(points, descriptors)


def verify_pair(
    a: Features, b: Features, ratio: float = 0.8, ransac_px: float = 3.0
) -> tuple[int, float]:
    """-> (fundamental-matrix RANSAC inliers, inliers / ratio-test matches); (0, 0.0) when
    fewer than 8 matches survive the ratio test."""
    if len(a.descriptors) < 2 or len(b.descriptors) < 2:
        return 0, 0.0
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    good = [m for m, n in (p for p in pairs if len(p) == 2) if m.distance < ratio * n.distance]
    if len(good) < 8:
        return 0, 0.0
    pa = a.keypoints[[m.queryIdx for m in good]]
    pb = b.keypoints[[m.trainIdx for m in good]]
    _, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, ransac_px, 0.999)
    inliers = int(mask.sum()) if mask is not None else 0
    return inliers, inliers / len(good)
