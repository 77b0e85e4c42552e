"""Raw ``sensor_msgs/Image`` fields -> RGB uint8: the encodings, the strided view, the conversion.

The encodings and their rules are listed in :mod:`pair_vpr_ros.images.convert`
(``SUPPORTED_ENCODINGS``).
"""

from __future__ import annotations

import operator
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from pair_vpr_ros.errors import ImageConversionError
from pair_vpr_ros.images.pixels import MAX_PIXELS, as_bytes, check_pixels, scale_to_uint8


@dataclass(frozen=True)
class _Spec:
    """How one raw encoding lies in memory and how it becomes RGB."""

    channels: int  # samples per pixel in a buffer row
    dtype: str  # sample type without byte order: "u1", "u2", "f4"
    kind: str  # "colour", "scaled", "bayer", "yuv422", "nv"
    code: int | None  # cv2 colour-conversion code; None: the samples already are RGB


_SPECS: dict[str, _Spec] = {
    "rgb8": _Spec(3, "u1", "colour", None),
    "bgr8": _Spec(3, "u1", "colour", cv2.COLOR_BGR2RGB),
    "rgba8": _Spec(4, "u1", "colour", cv2.COLOR_RGBA2RGB),
    "bgra8": _Spec(4, "u1", "colour", cv2.COLOR_BGRA2RGB),
    "8uc3": _Spec(3, "u1", "colour", cv2.COLOR_BGR2RGB),
    "8uc4": _Spec(4, "u1", "colour", cv2.COLOR_BGRA2RGB),
    "mono8": _Spec(1, "u1", "colour", cv2.COLOR_GRAY2RGB),
    "8uc1": _Spec(1, "u1", "colour", cv2.COLOR_GRAY2RGB),
    "rgb16": _Spec(3, "u2", "colour", None),
    "bgr16": _Spec(3, "u2", "colour", cv2.COLOR_BGR2RGB),
    "rgba16": _Spec(4, "u2", "colour", cv2.COLOR_RGBA2RGB),
    "bgra16": _Spec(4, "u2", "colour", cv2.COLOR_BGRA2RGB),
    "16uc3": _Spec(3, "u2", "colour", cv2.COLOR_BGR2RGB),
    "16uc4": _Spec(4, "u2", "colour", cv2.COLOR_BGRA2RGB),
    "mono16": _Spec(1, "u2", "scaled", None),
    "16uc1": _Spec(1, "u2", "scaled", None),
    "32fc1": _Spec(1, "f4", "scaled", None),
    "uyvy": _Spec(2, "u1", "yuv422", cv2.COLOR_YUV2RGB_UYVY),
    "yuv422": _Spec(2, "u1", "yuv422", cv2.COLOR_YUV2RGB_UYVY),
    "yuyv": _Spec(2, "u1", "yuv422", cv2.COLOR_YUV2RGB_YUY2),
    "yuv422_yuy2": _Spec(2, "u1", "yuv422", cv2.COLOR_YUV2RGB_YUY2),
    "nv21": _Spec(1, "u1", "nv", cv2.COLOR_YUV2RGB_NV21),
    "nv12": _Spec(1, "u1", "nv", cv2.COLOR_YUV2RGB_NV12),
}
_BAYER = {
    "rggb": cv2.COLOR_BayerRGGB2RGB,
    "bggr": cv2.COLOR_BayerBGGR2RGB,
    "gbrg": cv2.COLOR_BayerGBRG2RGB,
    "grbg": cv2.COLOR_BayerGRBG2RGB,
}
for _pattern, _code in _BAYER.items():
    _SPECS[f"bayer_{_pattern}8"] = _Spec(1, "u1", "bayer", _code)
    _SPECS[f"bayer_{_pattern}16"] = _Spec(1, "u2", "bayer", _code)
del _pattern, _code

_CANONICAL = {name.lower(): name for name in ("8UC1", "8UC3", "8UC4", "16UC1", "16UC3", "16UC4")}
_CANONICAL["32fc1"] = "32FC1"
SUPPORTED_ENCODINGS: tuple[str, ...] = tuple(_CANONICAL.get(name, name) for name in _SPECS)


def _check_size(value: Any, name: str, where: str) -> int:
    try:
        number = operator.index(value)
    except TypeError as err:
        raise ImageConversionError(f"{where}: {name} must be an integer, got {value!r}") from err
    if number <= 0:
        raise ImageConversionError(f"{where}: {name} must be positive")
    return number


def image_to_rgb(
    encoding: str,
    height: int,
    width: int,
    step: int,
    data: Any,
    is_bigendian: bool = False,
    max_pixels: int = MAX_PIXELS,
) -> np.ndarray:
    """Raw ``sensor_msgs/Image`` fields -> RGB uint8 [height, width, 3] (see module docstring)."""
    view, spec, where = image_samples(
        encoding, height, width, step, data, is_bigendian, max_pixels
    )
    try:
        return _convert(view, spec)
    except cv2.error as err:
        raise ImageConversionError(f"{where}: OpenCV could not convert it ({err})") from err


def image_samples(
    encoding: str,
    height: int,
    width: int,
    step: int,
    data: Any,
    is_bigendian: bool = False,
    max_pixels: int = MAX_PIXELS,
) -> tuple[np.ndarray, _Spec, str]:
    """Raw ``sensor_msgs/Image`` fields, checked -> (strided view [rows, W, C] of the samples in
    their byte order, the encoding's spec, a description for error messages); no copy."""
    fields = f"Image (encoding={encoding!r}, height={height}, width={width}, step={step}"
    buf = as_bytes(data, fields + ")")
    where = f"{fields}, len(data)={buf.size})"
    spec = _SPECS.get(str(encoding).strip().lower())
    if spec is None:
        raise ImageConversionError(
            f"{where}: unsupported encoding; supported: {', '.join(SUPPORTED_ENCODINGS)}"
        )
    h = _check_size(height, "height", where)
    w = _check_size(width, "width", where)
    step = _check_size(step, "step", where)
    check_pixels(w, h, max_pixels, where)
    if spec.kind == "yuv422" and w % 2:
        raise ImageConversionError(f"{where}: width must be even for 4:2:2 YUV")
    if spec.kind == "nv" and (w % 2 or h % 2):
        raise ImageConversionError(f"{where}: height and width must be even for 4:2:0 YUV")
    rows = h * 3 // 2 if spec.kind == "nv" else h
    itemsize = int(spec.dtype[1])
    bpp = spec.channels * itemsize
    if step < w * bpp:
        raise ImageConversionError(
            f"{where}: step is smaller than width * {bpp} bytes per pixel = {w * bpp}"
        )
    need = step * (rows - 1) + w * bpp
    if buf.size < need:
        raise ImageConversionError(
            f"{where}: data too short, need at least step * ({rows} - 1) + width * {bpp} "
            f"= {need} bytes"
        )
    dtype = np.dtype((">" if is_bigendian else "<") + spec.dtype if itemsize > 1 else spec.dtype)
    shape = (rows, w, spec.channels)
    return np.ndarray(shape, dtype, buffer=buf, strides=(step, bpp, itemsize)), spec, where


def _convert(view: np.ndarray, spec: _Spec) -> np.ndarray:
    """Strided samples [rows, W, C] -> RGB uint8 [H, W, 3]."""
    if spec.kind == "scaled":
        return cv2.cvtColor(scale_to_uint8(view[:, :, 0]), cv2.COLOR_GRAY2RGB)
    if spec.kind == "bayer":
        # OpenCV demosaics 16-bit data; keeping the high byte afterwards loses least.
        rgb = cv2.cvtColor(np.ascontiguousarray(view[:, :, 0], dtype=spec.dtype), spec.code)
        return (rgb >> 8).astype(np.uint8) if rgb.dtype == np.uint16 else rgb
    if spec.kind == "nv":
        return cv2.cvtColor(np.ascontiguousarray(view[:, :, 0]), spec.code)
    if view.dtype.itemsize == 2:
        view = (view >> 8).astype(np.uint8)
    if spec.code is None:
        return np.array(view, dtype=np.uint8, order="C")
    src = view[:, :, 0] if spec.channels == 1 else view
    return cv2.cvtColor(np.ascontiguousarray(src), spec.code)
