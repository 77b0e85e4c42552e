"""Features, matching and fundamental-matrix verification on synthetic views (SIFT and ORB)."""

from __future__ import annotations

import cv2
import numpy as np

from pair_vpr_ros.geometry import extract_features, match_features, verify_pair


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


def test_orb_features_verify_too():
    scene = textured(5)
    shifted = cv2.warpAffine(scene, np.float32([[1, 0, 9], [0, 1, 4]]), (320, 240))
    a, b = extract_features(scene, "orb"), extract_features(shifted, "orb")
    assert a.descriptors.shape[1] == 32 and a.descriptors.dtype == np.uint8
    inliers, _ = verify_pair(a, b)
    assert inliers >= 50
    assert verify_pair(a, extract_features(shifted)) == (0, 0.0)  # ORB vs SIFT: no matches


def test_matches_are_mutual_nearest_neighbours():
    scene = textured(6)
    shifted = cv2.warpAffine(scene, np.float32([[1, 0, 12], [0, 1, -7]]), (320, 240))
    a, b = extract_features(scene), extract_features(shifted)
    pairs = match_features(a, b)
    one_way = match_features(a, b, mutual=False)
    assert 40 <= len(pairs) <= len(one_way)
    assert len(set(pairs[:, 1].tolist())) == len(pairs)  # each b point matched once
    moved = b.keypoints[pairs[:, 1]] - a.keypoints[pairs[:, 0]]
    assert np.median(np.abs(moved - (12, -7)), axis=0).max() < 0.5


def test_keypoints_take_their_depth():
    feats = extract_features(textured(7), depth=np.full((240, 320), 3.0, np.float32))
    assert feats.depth.shape == (len(feats),) and (feats.depth == 3.0).all()
