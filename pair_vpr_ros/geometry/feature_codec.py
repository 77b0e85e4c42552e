"""The compact form of keyframe features in the place map (features record version 2, issue 34).

A keyframe keeps its strongest keypoints (detector response; SIFT 500, ORB 1000), keypoints
as uint16 steps of at most 1/64 px from the record's origin, depth as float16 (NaN stays NaN;
1 mm steps at 2 m, far below the depth noise) and SIFT descriptors in 4 bits a value: each value
v of a descriptor with largest value m is stored as q = round(15 sqrt(v / m)), given back as
m (q / 15)^2 (square-root levels, as RootSIFT: fine steps for the many small values, where the
L2 distance between SIFT descriptors is decided). ORB descriptors are binary and stay as they
are. 500 SIFT keypoints with depth take 35.6 KB instead of 140 KB for 1000 in version 1; the
poses they give are in docs/performance.md ("Compact keyframes").
"""

from __future__ import annotations

import numpy as np

# Keypoints a compact record keeps: SIFT's 500 strongest pose the TUM pairs as well as 1000 do;
# ORB needs more (27 of 28 TUM pairs posed with 500) and its 32-byte descriptors cost less.
COMPACT_KEEP = {"sift": 500, "orb": 1000}
_LEVELS = 15  # 4-bit descriptor values 0..15
_MAX_STEP = 1.0 / 64  # px: keypoint rounding far below a keypoint's own accuracy


def strongest(response: np.ndarray | None, count: int, keep: int) -> np.ndarray:
    """Indices of the `keep` keypoints of largest response, in their original order (the first
    `keep` when the responses are unknown) -> [min(count, keep)] int64."""
    if count <= keep:
        return np.arange(count)
    if response is None or len(response) != count:
        return np.arange(keep)
    # stable: equal responses keep the detector's order, so a record packs the same every time
    return np.sort(np.argsort(-np.asarray(response, np.float64), kind="stable")[:keep])


def keypoint_grid(kp: np.ndarray) -> tuple[float, float, float]:
    """(origin x, origin y, step px) of the uint16 grid the keypoints [M, 2] are stored on."""
    if not len(kp):
        return 0.0, 0.0, _MAX_STEP
    lo = kp.min(axis=0).astype(np.float64)
    span = float((kp.max(axis=0) - lo).max())
    # step: at most 1/64 px; larger only for keypoints over 1024 px apart (still below 1/16 px
    # up to 4096 px). float32-rounded so both sides of the record use the same value.
    step = float(np.float32(max(_MAX_STEP, span / 65000.0)))
    return float(np.float32(lo[0])), float(np.float32(lo[1])), step


def encode_keypoints(kp: np.ndarray, grid: tuple[float, float, float]) -> bytes:
    origin = np.array(grid[:2], np.float64)
    q = np.rint((kp.astype(np.float64) - origin) / grid[2])
    return np.clip(q, 0, 65535).astype("<u2").tobytes()


def decode_keypoints(data: bytes, n: int, grid: tuple[float, float, float]) -> np.ndarray:
    """-> keypoints [n, 2] float32."""
    q = np.frombuffer(data, "<u2", n * 2).reshape(n, 2).astype(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):  # a damaged grid: checked by the caller
        return (q * grid[2] + np.array(grid[:2], np.float64)).astype(np.float32)


def sift_bytes(n: int) -> int:
    return n + n * 64  # one byte for each descriptor's largest value, 64 bytes of 4-bit values


def encode_sift(desc: np.ndarray) -> bytes:
    """SIFT descriptors [M, 128] uint8 -> their 4-bit square-root form (`sift_bytes(M)`)."""
    top = desc.max(axis=1).astype(np.uint8)  # [M]
    safe = np.maximum(top, 1).astype(np.float32)[:, None]
    q = np.rint(_LEVELS * np.sqrt(desc.astype(np.float32) / safe)).astype(np.uint8)
    packed = q[:, 0::2] | (q[:, 1::2] << 4)
    return top.tobytes() + packed.tobytes()


def decode_sift(data: bytes, n: int) -> np.ndarray:
    """Inverse of `encode_sift` -> descriptors [n, 128] uint8 (each value within half a level)."""
    raw = np.frombuffer(data, np.uint8, sift_bytes(n))
    top = raw[:n].astype(np.float32)[:, None]
    packed = raw[n:].reshape(n, 64)
    q = np.empty((n, 128), np.float32)
    q[:, 0::2] = packed & 0x0F
    q[:, 1::2] = packed >> 4
    return np.rint(top * (q / _LEVELS) ** 2).astype(np.uint8)
