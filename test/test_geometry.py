"""ORB + ratio test + fundamental-matrix RANSAC on synthetic views."""

from __future__ import annotations

import cv2
import numpy as np

from pair_vpr_ros.geometry import extract_features, verify_pair


def textured(seed: int, shape=(240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.full((*shape, 3), 90, np.uint8)
    for _ in range(120):
        x, y = rng.integers(0, shape[1]), rng.integers(0, shape[0])
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        cv2.rectangle(
            img,
            (int(x), int(y)),
            (int(x) + int(rng.integers(5, 30)), int(y) + int(rng.integers(5, 30))),
            colour,
            -1,
        )
    return img


def test_same_scene_from_shifted_view_verifies():
    scene = textured(0)
    shifted = cv2.warpAffine(scene, np.float32([[1, 0, 12], [0, 1, -7]]), (320, 240))
    inliers, ratio = verify_pair(extract_features(scene), extract_features(shifted))
    assert inliers >= 50 and ratio > 0.5


def test_different_scenes_do_not_verify():
    inliers, _ = verify_pair(extract_features(textured(1)), extract_features(textured(2)))
    assert inliers < 15


def test_featureless_images_give_zero():
    flat = extract_features(np.zeros((60, 80, 3), np.uint8))
    assert flat.keypoints.shape == (0, 2)
    assert verify_pair(flat, extract_features(textured(3))) == (0, 0.0)


def test_large_images_are_downscaled_but_points_stay_in_pixels():
    big = cv2.resize(textured(4), (1280, 960), interpolation=cv2.INTER_NEAREST)
    feats = extract_features(big, max_side=640)
    assert feats.keypoints[:, 0].max() > 700  # coordinates in the original image
