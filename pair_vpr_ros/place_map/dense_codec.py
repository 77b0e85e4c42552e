"""How one keyframe's dense tokens [N, D] are stored: "q4" (default) or "f16" (uncompressed).

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

CODECS = ("q4", "f16")
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
    return (n * d + 1) // 2 + 2 * d


def encode(tokens: np.ndarray, codec: str) -> bytes:
    """tokens [N, D] float16 (finite, C-contiguous) -> the stored bytes."""
    if codec == "f16":
        return tokens.tobytes()
    x = tokens.astype(np.float32)
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
    raw = np.frombuffer(data, np.uint8)
    nibbles = (n * d + 1) // 2
    scale = np.frombuffer(raw[nibbles:].tobytes(), np.float16).astype(np.float32)
    q = np.empty(2 * nibbles, np.int8)
    q[0::2] = raw[:nibbles] & 0x0F
    q[1::2] = raw[:nibbles] >> 4
    values = (q[: n * d].reshape(n, d) - 8).astype(np.float32) * scale[None, :]
    return values.astype(np.float16)
