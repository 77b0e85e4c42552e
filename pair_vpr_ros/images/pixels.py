"""Pixel basics shared by raw and encoded images: message bytes, the size limit, scaling to uint8.

Scaling of a single-channel image (mono16 / 16UC1 / 32FC1, 16-bit grey PNGs, compressedDepth): the
range is the 1st..99th percentile of the finite values of a subsample, see `scale_to_uint8`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from pair_vpr_ros.errors import ImageConversionError, ImageTooLargeError

_SAMPLES = 16384  # pixels used to estimate the scaling percentiles
MAX_PIXELS = 50_000_000  # default size limit (width * height): 8K video is 33 MP


def as_bytes(data: Any, what: str) -> np.ndarray:
    """Message data (bytes, array.array, list, numpy uint8) -> flat uint8 array [L], no copy."""
    try:
        if isinstance(data, np.ndarray):
            if data.dtype != np.uint8:
                raise ImageConversionError(f"{what}: data must be uint8, got dtype {data.dtype}")
            return np.ascontiguousarray(data).reshape(-1)
        if isinstance(data, (bytes, bytearray, memoryview)) or hasattr(data, "buffer_info"):
            return np.frombuffer(data, dtype=np.uint8)
        if isinstance(data, (list, tuple)):
            return np.asarray(data, dtype=np.uint8)
    except (TypeError, ValueError, OverflowError) as err:
        raise ImageConversionError(f"{what}: data is not a byte buffer ({err})") from err
    raise ImageConversionError(
        f"{what}: data must be bytes, array.array, a list of ints or a uint8 numpy array, "
        f"got {type(data).__name__}"
    )


def scale_to_uint8(values: np.ndarray) -> np.ndarray:
    """Robustly scale a single-channel image [H, W] (any real dtype) to uint8 [H, W].

    Range: 1st..99th percentile of the finite values of a subsample (full finite min..max if those
    are equal); non-finite pixels and images without contrast give 0.
    """
    h, w = values.shape
    s = max(1, int(math.sqrt(h * w / _SAMPLES)))
    sample = values[::s, ::s].astype(np.float64).ravel()
    is_float = values.dtype.kind == "f"
    if is_float:
        sample = sample[np.isfinite(sample)]
    if sample.size == 0:
        return np.zeros((h, w), np.uint8)
    lo, hi = np.percentile(sample, [1.0, 99.0])
    if hi <= lo:
        full = values[np.isfinite(values)] if is_float else values
        lo, hi = float(full.min()), float(full.max())
        if hi <= lo:
            return np.zeros((h, w), np.uint8)
    scale = 255.0 / (hi - lo)
    out = values.astype(np.float32)
    with np.errstate(over="ignore", invalid="ignore"):  # extreme outliers just saturate
        out -= np.float32(lo - 0.5 / scale)  # the +0.5 rounds to nearest in the final cast
        out *= np.float32(scale)
        if is_float:  # non-finite input -> 0; overflowed finite outliers -> clipped to 0 / 255
            out[~np.isfinite(values)] = 0.0
    np.clip(out, 0.0, 255.0, out=out)
    return out.astype(np.uint8)


def check_pixels(width: int, height: int, max_pixels: int, where: str) -> None:
    """ImageTooLargeError when width * height exceeds `max_pixels`."""
    if width * height > max_pixels:
        raise ImageTooLargeError(
            f"{where}: the image is {width} x {height} = {width * height:,} pixels, more than "
            f"the limit of {max_pixels:,} (max_image_pixels): skipped; raise the limit if the "
            "camera really sends images this large"
        )
