"""Keypoints and descriptors of one keyframe (SIFT or ORB), depth at the keypoints, matching.

SIFT is the default: on the demo world's loop pairs it gives half the pose error of ORB at the
same success rate, and fewer, better keypoints make matching and RANSAC cheaper; its extraction
costs more (docs/relative-pose.md). SIFT descriptors are integers 0..255 in OpenCV, so both
kinds are stored as uint8 without loss.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import cv2
import numpy as np

from pair_vpr_ros.errors import GeometryInputError
from pair_vpr_ros.geometry.camera import PACKED_SIZE, CameraModel
from pair_vpr_ros.geometry.depth_noise import robust_depth_at, sigma_at
from pair_vpr_ros.geometry.feature_codec import (
    COMPACT_KEEP,
    decode_keypoints,
    decode_sift,
    encode_keypoints,
    encode_sift,
    keypoint_grid,
    sift_bytes,
    strongest,
)

KINDS = {"sift": 128, "orb": 32}  # descriptor bytes


@dataclass
class Features:
    """keypoints [M, 2] float32 distorted pixels; descriptors [M, 128 | 32] uint8; depth [M]
    float32 metres along the optical axis (NaN: unknown) or None without a depth image;
    camera: the intrinsics of the image (None: unknown); response [M] float32: the detector's
    strength of each keypoint (None: unknown; not stored, picks what a compact record keeps);
    depth_sigma [M] float32: the depth's own std (m) where the sensor gives one (stereo
    matching), NaN or None: the depth-noise model's."""

    keypoints: np.ndarray
    descriptors: np.ndarray
    kind: str = "sift"
    depth: np.ndarray | None = None
    camera: CameraModel | None = None
    response: np.ndarray | None = None
    depth_sigma: np.ndarray | None = None
    _float: np.ndarray | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.keypoints)

    def matchable(self) -> np.ndarray:
        """Descriptors as the matcher wants them (float32 for SIFT), cached."""
        if self.kind == "orb":
            return self.descriptors
        if self._float is None:
            self._float = self.descriptors.astype(np.float32)
        return self._float


def empty_features(kind: str = "sift") -> Features:
    return Features(np.zeros((0, 2), np.float32), np.zeros((0, KINDS[kind]), np.uint8), kind)


def _detector(kind: str, max_features: int):
    if kind == "sift":
        # A lower contrast threshold than OpenCV's 0.04: flat-shaded, fogged or dusk images
        # otherwise give too few keypoints for a pose (on the demo world's seed-8 loops 0.01
        # posed 99 % of them, 0.02 92 %, 0.04 67 %).
        return cv2.SIFT_create(max_features, contrastThreshold=0.01)
    if kind == "orb":
        return cv2.ORB_create(
            max_features, fastThreshold=7, edgeThreshold=15, patchSize=15, nlevels=4
        )
    raise GeometryInputError(f"unknown feature kind {kind!r}: choose one of {', '.join(KINDS)}")


def extract_features(
    rgb: np.ndarray,
    kind: str = "sift",
    max_features: int = 1000,
    max_side: int = 640,
    depth: np.ndarray | None = None,
    camera: CameraModel | None = None,
    depth_noise: tuple[float, float] = (0.0012, 0.0019),
    depth_sigma: np.ndarray | None = None,
) -> Features:
    """RGB uint8 [H, W, 3] (+ aligned depth [H, W] metres) -> Features; images larger than
    `max_side` are detected on a downscaled copy, keypoints stay in full-size pixels. The depth
    of a keypoint: `depth_noise.robust_depth_at` with sigma_z = a + b z^2, (a, b) =
    `depth_noise`; `depth_sigma` [H, W] (m, NaN: none): the depth's own std per pixel
    (stereo), kept at the keypoints as `Features.depth_sigma`."""
    grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    h, w = grey.shape
    scale = min(1.0, max_side / max(h, w))
    if scale < 1.0:  # each side at least 1 pixel: a 1 x 20000 strip must not become 0 x 640
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    keypoints, descriptors = _detector(kind, max_features).detectAndCompute(grey, None)
    if descriptors is None or not keypoints:
        out = empty_features(kind)
    else:
        to_full = np.array([w / grey.shape[1], h / grey.shape[0]], np.float32)
        points = np.array([kp.pt for kp in keypoints], np.float32) * to_full
        out = Features(points, np.clip(descriptors, 0, 255).astype(np.uint8), kind)
        out.response = np.array([kp.response for kp in keypoints], np.float32)
    out.camera = camera
    if depth is not None:
        out.depth = robust_depth_at(depth, out.keypoints, *depth_noise)
        if depth_sigma is not None and depth_sigma.shape == depth.shape:
            out.depth_sigma = sigma_at(depth_sigma, out.keypoints, out.depth)
    return out


def match_features(
    a: Features, b: Features, ratio: float = 0.8, mutual: bool = True
) -> np.ndarray:
    """Nearest-neighbour matches a -> b passing Lowe's ratio test (and, with `mutual`, whose
    b -> a nearest neighbour is the same point) -> [K, 2] int indices (into a, into b)."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    if a.kind != b.kind:
        raise GeometryInputError(f"cannot match {a.kind} features against {b.kind} features")
    norm = cv2.NORM_HAMMING if a.kind == "orb" else cv2.NORM_L2
    matcher = cv2.BFMatcher(norm)
    da, db = a.matchable(), b.matchable()
    pairs = matcher.knnMatch(da, db, k=2)
    good = [(m.queryIdx, m.trainIdx) for m, n in pairs if m.distance < ratio * n.distance]
    if not good:
        return np.zeros((0, 2), np.int64)
    out = np.array(good, np.int64)
    if mutual:
        back = matcher.match(db, da)
        best_in_a = np.full(len(b), -1, np.int64)
        best_in_a[[m.queryIdx for m in back]] = [m.trainIdx for m in back]
        out = out[best_in_a[out[:, 1]] == out[:, 0]]
    return out


_HEADER = struct.Struct("<4sBBBBIH2x")  # magic, version, kind, depth flags, has camera, M, width
_DEPTH, _SIGMA = 1, 2  # depth flags: depth stored; its own std stored after it (stereo)
_GRID = struct.Struct("<fff")  # version 2: keypoint grid origin x, y and step (px)
_KIND_CODES = {kind: i for i, kind in enumerate(KINDS)}


def pack_features(f: Features, compact: bool = True, keep: int | None = None) -> bytes:
    """Features -> bytes for the place map, little-endian: header, camera record, then
    compact (version 2, feature_codec.py: the `keep` strongest keypoints as uint16, 4-bit SIFT
    descriptors, float16 depth; `keep` default: COMPACT_KEEP of the kind) or full (version 1:
    keypoints [M, 2] float32, descriptors [M, W] uint8, depth [M] float32 when known). The
    depth's own std (`depth_sigma`) follows the depth in the same type."""
    sigma = f.depth_sigma if f.depth is not None else None
    if compact:
        pick = strongest(f.response, len(f.keypoints), keep or COMPACT_KEEP[f.kind])
        f = Features(f.keypoints[pick], f.descriptors[pick], f.kind,
                     None if f.depth is None else f.depth[pick], f.camera)  # fmt: skip
        sigma = None if sigma is None else sigma[pick]
    depths = [] if f.depth is None else [f.depth] + ([] if sigma is None else [sigma])
    n, width = f.descriptors.shape
    parts = [
        _HEADER.pack(
            b"FEAT",
            2 if compact else 1,
            _KIND_CODES[f.kind],
            (_DEPTH if depths else 0) | (_SIGMA if len(depths) == 2 else 0),
            f.camera is not None,
            n,
            width,
        ),  # fmt: skip
        f.camera.pack() if f.camera is not None else b"\0" * PACKED_SIZE,
    ]
    desc = np.ascontiguousarray(f.descriptors, np.uint8)
    if compact:
        grid = keypoint_grid(f.keypoints)
        parts += [_GRID.pack(*grid), encode_keypoints(f.keypoints, grid)]
        parts.append(encode_sift(desc) if f.kind == "sift" else desc.tobytes())
        parts += [np.asarray(d, "<f4").astype("<f2").tobytes() for d in depths]
        return b"".join(parts)
    parts += [np.ascontiguousarray(f.keypoints, "<f4").tobytes(), desc.tobytes()]
    parts += [np.ascontiguousarray(d, "<f4").tobytes() for d in depths]
    return b"".join(parts)


def _sizes(version: int, kind: str, n: int, width: int, depths: int) -> tuple[int, ...]:
    """Bytes of (grid, keypoints, descriptors, depth (+ its std: `depths` arrays)) in a record
    of `version`."""
    if version == 1:
        return 0, n * 8, n * width, n * 4 * depths
    desc = sift_bytes(n) if kind == "sift" else n * width
    return _GRID.size, n * 4, desc, n * 2 * depths


def unpack_features(data: bytes) -> Features:
    """Inverse of `pack_features` (versions 1 and 2); GeometryInputError when the bytes are not
    a features record."""
    try:
        magic, version, code, flags, has_camera, n, width = _HEADER.unpack_from(data)
        kind = list(KINDS)[code]
        pos = _HEADER.size
        if magic != b"FEAT" or version not in (1, 2):
            raise ValueError(f"not a features record of version 1 or 2 (version {version})")
        camera = CameraModel.unpack(data[pos : pos + PACKED_SIZE]) if has_camera else None
        pos += PACKED_SIZE
        if flags not in (0, _DEPTH, _DEPTH | _SIGMA):
            raise ValueError(f"unknown depth flags {flags}")
        depths = (flags & _DEPTH) + (flags & _SIGMA) // _SIGMA
        sizes = _sizes(version, kind, n, width, depths)
        if width != KINDS[kind] or len(data) != pos + sum(sizes):
            raise ValueError("size or header mismatch")
    except (struct.error, IndexError, ValueError) as err:
        raise GeometryInputError(f"stored keyframe features are damaged ({err})") from err
    grid = _GRID.unpack_from(data, pos) if version == 2 else None
    pos += sizes[0]
    if grid is None:
        keypoints = np.frombuffer(data, "<f4", n * 2, pos).reshape(n, 2).astype(np.float32)
    else:
        keypoints = decode_keypoints(data[pos : pos + sizes[1]], n, grid)
    pos += sizes[1]
    if version == 2 and kind == "sift":
        descriptors = decode_sift(data[pos : pos + sizes[2]], n)
    else:
        descriptors = np.frombuffer(data, np.uint8, n * width, pos).reshape(n, width).copy()
    pos += sizes[2]
    stored = []
    for _ in range(depths):
        d = np.frombuffer(data, "<f4" if version == 1 else "<f2", n, pos).astype(np.float32)
        d[np.isinf(d)] = np.nan  # float16 overflow (over 65 km): none
        stored.append(d)
        pos += sizes[3] // depths
    out = Features(keypoints, descriptors, kind, stored[0] if stored else None, camera)
    out.depth_sigma = stored[1] if depths == 2 else None
    return out
