"""How one keyframe's dense tokens [N, D] are stored: "p4" (default), "q4", "q4a" or "f16".

"p4" (issue 34): a basis per map. The map's first BASIS_FROM entries are stored as q4 and their
float16 tokens kept in memory; at the next add a basis is fitted on them once (`Basis.fit`) and
every later entry is stored as the components y = (x - mean) E [N, D], each with a width fixed
for the whole map (bits from the components' spreads by reverse water-filling, `allocate`), so
every entry has the same layout and the same bytes as q4. With the pair decoder's first layer
W [C, D] (it sees the tokens only as W x) the basis is fitted on W x: E = W^T V with V the
principal axes of W x, so the coding error goes where the decoder looks least. The basis (mean,
E as float16, the widths) is written once into the dense file's head (`Basis.to_bytes`: magic,
CRC32), and the first entries are coded with it too in their slots while no save names the
file (their CRC32s in the head); decoding needs the file only, never the model. An entry: a
float16 low end and step per component [D] each, then per run of equal width (widest first)
its bit planes, each `np.packbits` of [N, m] bits. The encoder picks each component's grid
(`_grid`: its full range or a narrower one, clipping the tails) for the least squared error:
on the demo 2.7 dB less error than the full range, in the same layout. Decoding costs a
[N, live] x [live, D] product: 4x q4's time per ViT-B keyframe on free cores, up to 10x on busy
ones (docs/performance.md). The default: on the demo it changes 3 re-ranked winners of 520, q4 19.

"q4a" (issue 34): 4 bits a value on a grid of each channel's own range, x = (q - z) s with q in
0..15: the step s = base 2^(e / 16) (one uint8 e per channel, one float32 base per keyframe: the
step is at most 4.4 % above (max - min) / 15) and the zero point z (int8 per channel) centres the
16 levels on the channel's values. ViT tokens' channels sit off zero (on the demo model the mean
of a channel is 0.6 of its spread, median over channels), so a grid of their own range halves
the squared error of q4's grid around zero, in the same 203,136 + 1,536 + 4 = 204,676 bytes;
but on the demo model it picks the same re-ranked winners as q4, no more (docs/performance.md),
and unlike q4 it is not idempotent: tokens decoded and encoded again (a merge) move by up to a
step.
"q4": 4-bit symmetric quantisation with one float16 scale per channel (computed per keyframe):
q = round(x / s) in -7..7 with s = max |x| of the channel / 7, two values per byte, then the D
scales. ViT-B/322 (529 x 768): 203,136 + 1,536 = 204,672 bytes (200 KiB) instead of 812,544.
Per channel rather than per token because ViT tokens carry a few channels of much larger
magnitude in every token: a per-token scale would spend the 15 levels on them. The re-ranking's
tolerance is measured in docs/performance.md ("Compact keyframes").
"f16": the tokens as float16, byte for byte the layout of maps of format versions 1 and 2.
"""

from __future__ import annotations

import functools
import heapq
import struct
import zlib

import numpy as np

from pair_vpr_ros.errors import ConfigError, MapError

CODECS = ("p4", "q4a", "q4", "f16")
DEFAULT_CODEC = "p4"  # what a new map uses (IndexConfig, compact, the node's dense_codec)
# p4: the keyframes the basis is fitted on (module docstring); part of the format: it sizes the
# head of every p4 file, so another value needs another codec name
BASIS_FROM = 16
# p4's head: magic, CRC32 of the rest, first entry coded with the basis, D, copies of entries
# before it (see `Basis`)
_HEAD = struct.Struct("<4sIIII")
_MAGIC = b"PVB1"
_PAD = 36  # p4: bytes an entry keeps for padding its bit planes (at most 36) to whole bytes
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
    q4 = (n * d + 1) // 2 + 2 * d
    return q4 + 4 if codec == "q4a" else max(q4, 4 * d + _PAD) if codec == "p4" else q4


def head_bytes(shape: tuple[int, int], codec: str) -> int:
    """Bytes before entry 0 in a dense file of `codec`: p4's basis (zeros until it is fitted)."""
    d = int(shape[1])
    return _HEAD.size + 4 * d + 2 * d * d + d + 4 * BASIS_FROM if codec == "p4" else 0


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


# ------------------------------------------------------------------------------------- p4
def allocate(energy: np.ndarray, total: int, top: int = 8) -> np.ndarray:
    """Bits 0..top for each component of energy [D] (its mean squared range), `total` in all:
    each bit goes where it removes the most squared error (energy 4^-bits), reverse
    water-filling for a uniform quantiser."""
    bits = np.zeros(len(energy), np.int64)
    heap = [(-float(e), i) for i, e in enumerate(energy)]
    heapq.heapify(heap)
    for _ in range(min(int(total), top * len(energy))):
        e, i = heapq.heappop(heap)
        bits[i] += 1
        if bits[i] < top:
            heapq.heappush(heap, (e / 4, i))
    return bits


def _toward(values: np.ndarray, down: bool) -> np.ndarray:
    """float32 [D] -> float16, rounded down (or up), within float16's range."""
    v = np.clip(values, -65504, 65504).astype(np.float32)
    h = v.astype(np.float16)
    off = h.astype(np.float32) > v if down else h.astype(np.float32) < v
    return np.where(off, np.nextafter(h, np.float16(-np.inf if down else np.inf)), h)


# p4's grids: fractions of the full-range step tried for each component of an entry; below 1
# the grid clips the component's tails (most of a bell-shaped component's values are near its
# centre: at 1-3 bits a range of its extremes leaves them between few, far levels)
_SHRINK = np.array([1, 0.85, 0.72, 0.62, 0.53, 0.45, 0.38, 0.32, 0.27, 0.23, 0.19], np.float32)


def _grid(y: np.ndarray, levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Components y [N, L] with levels [L] (2^bits - 1) -> the float16 low end and step [L] of
    each one's uniform grid of least squared error among `_SHRINK`'s (centred on the midrange;
    1: the full range, min to max); the error is that of the decoder's arithmetic, on every
    token up to 255, else on every k-th, 128-255 of them (ViT-B: 133, 4x less encode time)."""
    low, high = y.min(0), y.max(0)
    lo_full = _toward(low, down=True)
    span = (high - lo_full.astype(np.float32)) / np.maximum(levels, 1)
    best_err, best_lo, best_step = None, lo_full, lo_full
    y = y[:: max(1, len(y) // 128)]
    for shrink in _SHRINK:
        step = _toward(span * shrink, down=False)
        s32 = step.astype(np.float32)
        lo = lo_full if shrink == 1 else _toward((low + high - s32 * levels) / 2, down=True)
        l32 = lo.astype(np.float32)
        q = np.clip(np.rint((y - l32) / np.where(s32 > 0, s32, 1)), 0, levels)
        err = np.square(q * s32 + l32 - y).sum(0)  # [L]
        if best_err is None:
            best_err, best_lo, best_step = err, lo, step
            continue
        take = err < best_err
        best_err = np.where(take, err, best_err)
        best_lo, best_step = np.where(take, lo, best_lo), np.where(take, step, best_step)
    return best_lo, best_step


class Basis:
    """p4's transform of one map: y = (x - mean) @ enc, x = y @ dec + mean (dec = enc^-1),
    components ordered by their fixed widths `bits` [D] (widest first; `groups`: (width, first,
    stop) per run of equal width); `start`: the first entry coded with it; `recoded`: the
    CRC32s of entries 0.. before it that were coded with it too, in their own slots (from their
    float16 tokens, kept until the fit; only in a file no save names yet: none otherwise)."""

    def __init__(
        self, mean: np.ndarray, enc: np.ndarray, bits: np.ndarray, start: int, recoded=()
    ) -> None:
        self.mean = np.asarray(mean, "<f4")
        self.enc16 = np.asarray(enc, "<f2")
        self.bits = np.asarray(bits, np.uint8)
        self.start = int(start)
        self.enc = self.enc16.astype(np.float32)
        self.live = int(np.count_nonzero(self.bits))  # components with bits come first
        widths = self.bits[: self.live]
        cut = [0, *np.flatnonzero(np.diff(widths)) + 1, self.live]
        pairs = zip(cut[:-1], cut[1:], strict=True)
        self.groups = [(int(widths[a]), a, b) for a, b in pairs if b > a]
        self.recoded = [int(c) for c in recoded]
        crcs = np.asarray(self.recoded, "<u4").tobytes()
        self.payload = self.mean.tobytes() + self.enc16.tobytes() + self.bits.tobytes() + crcs
        fields = struct.pack("<III", self.start, len(mean), len(self.recoded))
        self.crc = zlib.crc32(self.payload, zlib.crc32(fields))

    @functools.cached_property
    def dec(self) -> np.ndarray:
        """enc^-1 [D, D] float32, made at the first decode (not at load: ~0.1 s at D = 768)."""
        return np.linalg.inv(self.enc.astype(np.float64)).astype(np.float32)

    @classmethod
    def fit(cls, x: np.ndarray, n: int, size: int, start: int, weight=None) -> Basis:
        """x [K * n, D]: the decoded tokens of K keyframes of n tokens; size: entry bytes;
        weight: the decoder's W [C, D] (used when square and well conditioned) or None."""
        x = x.astype(np.float64)
        mean = x.mean(0)
        w = None if weight is None else np.asarray(weight, np.float64)
        if w is not None and (w.shape != (x.shape[1],) * 2 or np.linalg.cond(w) > 1e4):
            w = None  # the fit falls back to the tokens' own channels
        z = (x - mean) if w is None else (x - mean) @ w.T
        vectors = np.linalg.eigh(z.T @ z)[1][:, ::-1]
        enc = vectors if w is None else w.T @ vectors
        enc = enc * 2.0 ** -np.ceil(np.log2(np.abs(enc).max()))  # float16's sweet spot
        enc16 = enc.astype(np.float16)
        y = ((x - mean) @ enc16.astype(np.float64)).reshape(-1, n, x.shape[1])
        energy = ((y.max(1) - y.min(1)) ** 2).mean(0)  # [D]
        d = x.shape[1]
        bits = allocate(energy, max(size - 4 * d - _PAD, 0) * 8 // n)
        order = np.argsort(-bits, kind="stable")
        return cls(mean, enc16[:, order], bits[order], start)

    def to_bytes(self) -> bytes:
        """The head of a p4 file; its CRC32 (`crc`) also seeds those of the entries coded with
        it, so entries never decode with a basis they were not coded with."""
        head = _HEAD.pack(_MAGIC, self.crc, self.start, len(self.mean), len(self.recoded))
        return head + self.payload

    @classmethod
    def from_bytes(cls, data: bytes, shape: tuple[int, int], where: str) -> Basis | None:
        """The head of a p4 file of entries [N, D] -> its basis, None when none was written yet
        (zeros); MapError when it is damaged."""
        if not any(data):
            return None
        magic, crc, start, dim, copies = _HEAD.unpack_from(data)
        d = int(shape[1])
        payload = data[_HEAD.size : _HEAD.size + 4 * d + 2 * d * d + d + 4 * copies]
        if (
            (magic, dim) != (_MAGIC, d)
            or copies > min(start, BASIS_FROM)
            or crc != zlib.crc32(payload, zlib.crc32(data[8:20]))
        ):
            raise MapError(
                f"the p4 basis at the head of {where} fails its check (magic, size or CRC32): "
                "the file is damaged on disk; restore the map from a backup or rebuild it"
            )
        mean = np.frombuffer(payload[: 4 * d], "<f4")
        enc = np.frombuffer(payload[4 * d : 4 * d + 2 * d * d], "<f2").reshape(d, d)
        at = 4 * d + 2 * d * d + d
        recoded = np.frombuffer(payload[at:], "<u4")
        return cls(mean, enc, np.frombuffer(payload[at - d : at], np.uint8), start, recoded)

    def encode(self, tokens: np.ndarray, size: int) -> bytes:
        """tokens [N, D] float16 -> `size` bytes."""
        y = (tokens.astype(np.float32) - self.mean) @ self.enc  # [N, D]
        levels = (2.0 ** self.bits.astype(np.float32) - 1).astype(np.float32)
        lo, step = np.zeros((2, len(self.mean)), np.float16)
        lo[: self.live], step[: self.live] = _grid(y[:, : self.live], levels[: self.live])
        lo[self.live :] = y[:, self.live :].mean(0)  # no bits: the component's mean
        safe = np.where(step > 0, step.astype(np.float32), 1)
        parts = [lo.tobytes(), step.tobytes()]
        for width, a, b in self.groups:
            q = np.rint((y[:, a:b] - lo[a:b].astype(np.float32)) / safe[a:b])
            q = np.clip(q, 0, levels[a]).astype(np.uint8).reshape(-1)
            parts += [np.packbits((q >> k) & 1, bitorder="little").tobytes() for k in range(width)]
        data = b"".join(parts)
        return data + bytes(size - len(data))

    def decode(self, data: bytes, n: int) -> np.ndarray:
        """Bytes of `encode` -> tokens [n, D] float16."""
        raw = np.frombuffer(data, np.uint8)
        d = len(self.mean)
        lo, step = np.frombuffer(data, "<f2", 2 * d).astype(np.float32).reshape(2, d)
        y = np.empty((n, self.live), np.float32)
        at = 4 * d
        for width, a, b in self.groups:
            plane = (n * (b - a) + 7) // 8
            bits = np.unpackbits(
                raw[at : at + width * plane].reshape(width, plane), axis=1,
                count=n * (b - a), bitorder="little",
            )  # fmt: skip
            q = bits[0].copy()
            for k in range(1, width):
                q |= bits[k] << k
            y[:, a:b] = q.reshape(n, b - a)
            at += width * plane
        y *= step[: self.live]
        y += lo[: self.live]
        rest = lo[self.live :] @ self.dec[self.live :] + self.mean  # [D]
        return (y @ self.dec[: self.live] + rest).astype(np.float16)
