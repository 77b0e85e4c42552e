"""Bad-input matrix, stored keyframe features records (geometry/features.py, versions 1 and 2):
a truncated, lengthened, foreign or unknown-version record is a GeometryInputError with the
exact reason; the pipeline counts it (`features_damaged`) and poses that loop without them;
a compact record whose keypoint grid says NaN or 1e30 px is refused by the fleet's check."""

from __future__ import annotations

import re
import struct
from types import SimpleNamespace

import numpy as np
import pytest

from pair_vpr_ros.errors import FleetMessageError, GeometryInputError
from pair_vpr_ros.fleet.owner import check_features
from pair_vpr_ros.geometry.camera import PACKED_SIZE
from pair_vpr_ros.geometry.features import Features, pack_features, unpack_features
from pair_vpr_ros.geometry.keyframes import KeyframeGeometry

GRID_AT = 16 + PACKED_SIZE  # the header, the camera record, then the grid (origin x, y, step)


def compact(n: int = 40) -> bytes:
    rng = np.random.default_rng(5)
    kp = rng.uniform(0, 320, (n, 2)).astype(np.float32)
    desc = rng.integers(0, 120, (n, 128), dtype=np.uint8)
    return pack_features(Features(kp, desc, "sift", rng.uniform(1, 5, n).astype(np.float32)))


def with_version(data: bytes, version: int) -> bytes:
    return data[:4] + bytes([version]) + data[5:]


def with_depth_flags(data: bytes, flags: int) -> bytes:
    return data[:6] + bytes([flags]) + data[7:]


def with_grid(data: bytes, *grid: float) -> bytes:
    return data[:GRID_AT] + struct.pack("<fff", *grid) + data[GRID_AT + 12 :]


CASES = {
    "truncated compact record": (lambda d: d[:-7], "size or header mismatch"),
    "compact record with a tail": (lambda d: d + b"\0", "size or header mismatch"),
    "header only": (lambda d: d[:16], "size or header mismatch"),
    "shorter than a header": (
        lambda d: d[:9],
        "unpack_from requires a buffer of at least 16 "
        "bytes for unpacking 16 bytes at offset 0 (actual buffer size is "
        "9)",
    ),  # fmt: skip
    "unknown version": (
        lambda d: with_version(d, 3),
        "not a features record of version 1 or 2 (version 3)",
    ),  # fmt: skip
    "version 1 size read as 2": (lambda d: with_version(d, 1), "size or header mismatch"),
    "depth flags of no kind": (lambda d: with_depth_flags(d, 4), "unknown depth flags 4"),
    "depth std without depth": (lambda d: with_depth_flags(d, 2), "unknown depth flags 2"),
    "depth std said, not stored": (lambda d: with_depth_flags(d, 3), "size or header mismatch"),
    "foreign magic": (
        lambda d: b"JPEG" + d[4:],
        "not a features record of version 1 or 2 (version 2)",
    ),  # fmt: skip
}


@pytest.mark.parametrize("case", CASES)
def test_a_bad_record_is_a_clear_error_and_counted(case: str) -> None:
    damage, reason = CASES[case]
    bad = damage(compact())
    message = f"stored keyframe features are damaged ({reason})"
    with pytest.raises(GeometryInputError, match=f"^{re.escape(message)}$"):
        unpack_features(bad)
    counts = SimpleNamespace(features_damaged=0)
    assert KeyframeGeometry(None, counts).unpack(bad) is None
    assert counts.features_damaged == 1


GRIDS = {
    "NaN origin": ((float("nan"), 0.0, 1 / 64), "keypoints are not finite [M, 2] pixels"),
    "inf step": ((0.0, 0.0, float("inf")), "keypoints are not finite [M, 2] pixels"),
    "1e30 origin": ((1e30, 0.0, 1 / 64), "keypoints beyond 1e+05 px"),
    "zero step": ((3.0, 3.0, 0.0), "most keypoints repeat one position"),
}


@pytest.mark.parametrize("case", GRIDS)
def test_a_compact_record_with_a_bad_grid_is_refused_by_the_fleet_check(case: str) -> None:
    grid, detail = GRIDS[case]
    features = unpack_features(with_grid(compact(), *grid))  # well-formed bytes: unpacked
    with pytest.raises(FleetMessageError, match=f"^bad features: {re.escape(detail)}$"):
        check_features(features)
