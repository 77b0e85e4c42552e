"""Keyframe features as the place map stores them: the compact record (version 2, the default)
keeps the strongest keypoints within 1/128 px, depth within float16 and SIFT values within
half a square-root level; the full record (version 1) and maps written before compact features
give back exactly what was stored."""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pair_vpr_ros.geometry import camera_from_params
from pair_vpr_ros.geometry.feature_codec import decode_sift, encode_sift
from pair_vpr_ros.geometry.features import Features, pack_features, unpack_features
from pair_vpr_ros.geometry.keyframes import GeometryConfig, KeyframeGeometry
from pair_vpr_ros.place_map import PlaceMap

MAPS = Path(__file__).resolve().parents[1] / "data" / "maps"


def fixture_features(i: int) -> Features:
    """The features of keyframe i of test/data/maps/format-3 (written by main at fff4a59)."""
    rng = np.random.default_rng(100 + i)
    n = 30
    kp = rng.uniform(0, 320, (n, 2)).astype(np.float32)
    if i == 1:
        return Features(kp, rng.integers(0, 256, (n, 32), dtype=np.uint8), "orb")
    desc = rng.integers(0, 120, (n, 128), dtype=np.uint8)
    depth = rng.uniform(0.5, 8, n).astype(np.float32)
    depth[::7] = np.nan
    cam = camera_from_params(320, 240, 250.0, 250.0, 160.0, 120.0)
    return Features(kp, desc, "sift", depth, cam)


def sift(n: int, seed: int = 0) -> Features:
    rng = np.random.default_rng(seed)
    f = Features(rng.uniform(0, 640, (n, 2)).astype(np.float32),
                 rng.integers(0, 140, (n, 128), dtype=np.uint8), "sift",
                 rng.uniform(0.3, 9, n).astype(np.float32))  # fmt: skip
    f.response = rng.uniform(0, 1, n).astype(np.float32)
    return f


def test_a_compact_record_keeps_the_strongest_keypoints_in_order_and_close() -> None:
    f = sift(1000)
    data = pack_features(f)
    back = unpack_features(data)
    keep = np.sort(np.argsort(-f.response)[:500])
    assert len(back) == 500 and len(data) < 36_000  # 140,000 B for the full record of 1000
    assert np.abs(back.keypoints - f.keypoints[keep]).max() <= 1 / 128 + 1e-4
    assert np.allclose(back.depth, f.depth[keep], rtol=2**-11)
    err = np.abs(back.descriptors.astype(int) - f.descriptors[keep].astype(int))
    # square-root levels: half a level is at most 9 at the top (140), less below
    assert err.mean() < 3.5 and err.max() <= 10 and err[f.descriptors[keep] < 20].max() <= 3
    assert back.response is None and back.kind == "sift"


def test_sift_values_of_zero_and_the_largest_come_back_exactly() -> None:
    desc = np.zeros((3, 128), np.uint8)
    desc[0, :5] = (0, 1, 50, 99, 140)
    desc[2, 7] = 255
    back = decode_sift(encode_sift(desc), 3)
    assert back[0, 0] == 0 and back[0, 4] == 140 and back[1].max() == 0 and back[2, 7] == 255


def test_a_full_record_and_orb_descriptors_come_back_bit_for_bit() -> None:
    f = sift(700)
    back = unpack_features(pack_features(f, compact=False))
    assert np.array_equal(back.keypoints, f.keypoints) and np.array_equal(back.depth, f.depth)
    assert np.array_equal(back.descriptors, f.descriptors)
    orb = fixture_features(1)
    back = unpack_features(pack_features(orb))
    assert np.array_equal(back.descriptors, orb.descriptors) and back.depth is None
    assert np.abs(back.keypoints - orb.keypoints).max() <= 1 / 128 + 1e-4


def test_empty_features_pack_both_ways() -> None:
    empty = Features(np.zeros((0, 2), np.float32), np.zeros((0, 128), np.uint8))
    for compact in (True, False):
        assert len(unpack_features(pack_features(empty, compact))) == 0


def test_the_parameter_picks_the_record_the_map_stores() -> None:
    counts = SimpleNamespace(features_damaged=0)
    f = sift(800)
    full = KeyframeGeometry(GeometryConfig(compact_features=False), counts).pack(f)
    assert len(unpack_features(full)) == 800
    assert len(unpack_features(KeyframeGeometry(None, counts).pack(f))) == 500


@pytest.mark.parametrize("read_only", [True, False])
def test_a_map_written_before_compact_features_gives_them_back(tmp_path, read_only) -> None:
    d = Path(shutil.copytree(MAPS / "format-3", tmp_path / "map"))
    geometry = KeyframeGeometry(None, SimpleNamespace(features_damaged=0))
    with PlaceMap.load(d, read_only=read_only) as m:
        for i in range(3):
            got, want = geometry.unpack(m.features(i)), fixture_features(i)
            assert got.kind == want.kind and got.camera == want.camera
            assert np.array_equal(got.keypoints, want.keypoints)
            assert np.array_equal(got.descriptors, want.descriptors)
            assert (got.depth is None) == (want.depth is None)
            if want.depth is not None:
                assert np.array_equal(got.depth, want.depth, equal_nan=True)
    assert geometry.counts.features_damaged == 0


def test_the_depths_own_std_comes_back_in_both_records() -> None:
    f = sift(800)
    f.depth_sigma = (0.01 * f.depth**2).astype(np.float32)
    f.depth_sigma[::7] = np.nan  # none there: the model's
    keep = np.sort(np.argsort(-f.response)[:500])
    back = unpack_features(pack_features(f))
    assert np.allclose(back.depth_sigma, f.depth_sigma[keep], rtol=2**-10, equal_nan=True)
    full = unpack_features(pack_features(f, compact=False))
    assert np.array_equal(full.depth_sigma, f.depth_sigma, equal_nan=True)
    f.depth_sigma = None
    assert unpack_features(pack_features(f)).depth_sigma is None
