"""How one keyframe's dense tokens [N, D] are stored: "q4" (default), "q4a" or "f16" (as given).

"q4a" (issue 34): 4 bits a value on a grid of each channel's own range, x = (q - z) s with q in
0..15: the step s = base 2^(e / 16) (one uint8 e per channel, one float32 base per keyframe: the
step is at most 4.4 % above (max - min) / 15) and the zero point z (int8 per channel) centres the
16 levels on the channel's values. ViT tokens' channels sit off zero (on the demo model the mean
of a channel is 0.6 of its spread, median over channels), so a grid of their own range halves
the squared error of q4's grid around zero, in the same 203,136 + 1,536 + 4 = 204,676 bytes;
but on the demo model it picks the same re-ranked winners as q4, no more (docs/performance.md),
and unlike q4 it is not idempotent: tokens decoded and encoded again (a merge) move by up to a
step. So q4 stays the default.
"q4": 4-bit symmetric quantisation with one float16 scale per channel (computed per keyframe):
q = round(x / s) in -7..7 with s = max |x| of the channel / 7, two values per byte, then the D
scales. ViT-B/322 (529 x 768): 203,136 + 1,536 = 204,672 bytes (200 KiB) instead of 812,544.
Per channel rather than per token because ViT tokens carry a few channels of much larger
magnitude in every token: a per-token scale would spend the 15 levels on them. The re-ranking's
tolerance is measured in docs/performance.md ("Compact keyframes").
"f16": the tokens as float16, byte for byte the layout of maps of format versions 1 and 2.
"""

from __future__ import annotations

import numpy as np

from pair_vpr_ros.errors import ConfigError

CODECS = ("q4a", "q4", "f16")
_LEVELS = 7  # |q| <= 7: symmetric, so 0 stays exactly 0


def check_codec(codec: str) -> str:
    if codec not in CODECS:
        raise ConfigError(f"dense_codec must be one of {CODECS}, got {codec!r}")
    return codec


def entry_bytes(shape: tuple[int, int], codec: str = "f16") -> int:
    """Bytes of one keyframe's dense tokens [N, D] as stored with `codec`."""
    n, d = int(shape[0]), int(shape[1])
    if codec == "f16":
        return n * d * 2
    return (n * d + 1) // 2 + 2 * d + (4 if codec == "q4a" else 0)


def _pack(q: np.ndarray) -> bytes:
    """Values 0..15 [M] -> two a byte."""
    if q.size % 2:
        q = np.append(q, np.uint8(0))
    return (q[0::2] | (q[1::2] << 4)).astype(np.uint8).tobytes()


def _unpack(raw: np.ndarray, count: int) -> np.ndarray:
    q = np.empty(2 * len(raw), np.int16)
    q[0::2] = raw & 0x0F
    q[1::2] = raw >> 4
    return q[:count]


def _steps(base: np.float32, e: np.ndarray) -> np.ndarray:
    """Per-channel steps [D] float32 from the codes e [D]: the same arithmetic both ways."""
    return (base * np.exp2(e.astype(np.float32) / np.float32(32))).astype(np.float32)


def _encode_q4a(x: np.ndarray) -> bytes:
    lo, hi = x.min(axis=0), x.max(axis=0)  # [D]
    # a step that spans the range in 15, and one that reaches the channel's centre with an int8
    # zero point (a constant channel far from 0)
    ideal = np.maximum((hi - lo) / np.float32(15), np.abs(lo + hi) / np.float32(240))
    top = float(ideal.max())
    base = np.float32(top * 2.0 ** (-255 / 32) if top > 0 else 1.0)
    with np.errstate(divide="ignore"):
        e = np.ceil(32 * np.log2(np.maximum(ideal, 1e-30) / base) - 1e-4)
    e = np.clip(e, 0, 255).astype(np.uint8)
    step = _steps(base, e)
    step = np.where(step * 15 < hi - lo, step * np.float32(1.05), step)  # float rounding
    z = np.clip(np.rint(7.5 - (lo + hi) / (2 * step)), -128, 127)
    q = np.clip(np.rint(x / step) + z, 0, 15).astype(np.uint8).reshape(-1)
    return _pack(q) + e.tobytes() + z.astype(np.int8).tobytes() + base.tobytes()


def _decode_q4a(data: bytes, n: int, d: int) -> np.ndarray:
    raw = np.frombuffer(data, np.uint8)
    nibbles = (n * d + 1) // 2
    e, z = raw[nibbles : nibbles + d], raw[nibbles + d : nibbles + 2 * d].view(np.int8)
    base = np.frombuffer(raw[nibbles + 2 * d :].tobytes(), np.float32)[0]
    q = _unpack(raw[:nibbles], n * d).reshape(n, d) - z.astype(np.int16)
    return (q.astype(np.float32) * _steps(base, e)).astype(np.float16)


def encode(tokens: np.ndarray, codec: str) -> bytes:
    """tokens [N, D] float16 (finite, C-contiguous) -> the stored bytes."""
    if codec == "f16":
        return tokens.tobytes()
    x = tokens.astype(np.float32)
    if codec == "q4a":
        return _encode_q4a(x)
    scale = (np.abs(x).max(axis=0) / _LEVELS).astype(np.float16)  # [D]
    safe = np.where(scale > 0, scale.astype(np.float32), 1.0)
    q = np.clip(np.rint(x / safe), -_LEVELS, _LEVELS).astype(np.int8).reshape(-1) + 8
    if q.size % 2:
        q = np.append(q, np.int8(8))
    packed = (q[0::2] | (q[1::2] << 4)).astype(np.uint8)
    return packed.tobytes() + scale.tobytes()


def decode(data: bytes, shape: tuple[int, int], codec: str) -> np.ndarray:
    """Stored bytes -> tokens [N, D] float16 (read-only when f16)."""
    n, d = shape
    if codec == "f16":
        return np.frombuffer(data, np.float16).reshape(shape)
    if codec == "q4a":
        return _decode_q4a(data, n, d)
    raw = np.frombuffer(data, np.uint8)
    nibbles = (n * d + 1) // 2
    scale = np.frombuffer(raw[nibbles:].tobytes(), np.float16).astype(np.float32)
    q = np.empty(2 * nibbles, np.int8)
    q[0::2] = raw[:nibbles] & 0x0F
    q[1::2] = raw[:nibbles] >> 4
    values = (q[: n * d].reshape(n, d) - 8).astype(np.float32) * scale[None, :]
    return values.astype(np.float16)
