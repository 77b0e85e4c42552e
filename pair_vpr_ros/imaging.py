"""ROS-free conversion of ``sensor_msgs/Image`` and ``CompressedImage`` data to RGB uint8.

Every function returns a fresh C-contiguous ``np.ndarray [H, W, 3] uint8`` in RGB order that never
shares memory with the message, and raises :class:`~pair_vpr_ros.errors.ImageConversionError`
(naming the encoding, the sizes and what is wrong) for anything unsupported or malformed.

Raw ``Image`` encodings (``SUPPORTED_ENCODINGS``, matched case-insensitively):

- 8-bit colour: ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``8UC3`` (= bgr8), ``8UC4`` (= bgra8);
  alpha is dropped.
- 16-bit colour: ``rgb16``, ``bgr16``, ``rgba16``, ``bgra16``, ``16UC3`` (= bgr16),
  ``16UC4`` (= bgra16): the high byte is kept (``>> 8``), as cv_bridge does.
- grey: ``mono8``, ``8UC1``; ``mono16``, ``16UC1``, ``32FC1`` are scaled (see below).
- Bayer: ``bayer_{rggb,bggr,gbrg,grbg}8`` and ``...16`` (demosaiced by OpenCV, 16-bit ``>> 8``).
- YUV: ``uyvy`` / ``yuv422`` (U Y V Y), ``yuyv`` / ``yuv422_yuy2`` (Y U Y V) need an even width;
  ``nv21`` / ``nv12`` (a Y plane of ``height`` rows then an interleaved VU / UV plane of
  ``height / 2`` rows, all rows ``step`` bytes apart) need even height and width.

Rows are read through ``step`` (padding allowed) and ``is_bigendian`` selects the byte order of
16-bit and float samples.

Scaling of mono16 / 16UC1 / 32FC1 (and of single-channel 16-bit PNGs and compressedDepth): the
range is the 1st..99th percentile of the finite values of a subsample (about 16k pixels, every s-th
row and column), so that a few hot pixels or far-away depth readings do not wash the image out; it
falls back to the full finite min..max when those percentiles are equal. Values are mapped linearly
to 0..255 and clipped; non-finite pixels become 0 and an image without contrast is all 0.

``CompressedImage`` formats: ``"jpeg"``, ``"jpg"``, ``"png"`` (also ``tiff``, ``webp``, ``bmp``),
the image_transport form ``"<enc>; jpeg compressed bgr8"`` and
``"<16UC1|32FC1>; compressedDepth png"`` (a 12-byte header before the PNG; 32FC1 depth is recovered
from the quantised inverse depth). Decoded colour is BGR(A) and becomes RGB, grey becomes RGB,
single-channel 16-bit is scaled as above and 16-bit colour is ``>> 8``.

Size limit: an image of more than ``max_pixels`` (width * height, default ``MAX_PIXELS`` = 50
megapixels, the node's ``max_image_pixels``) raises ``ImageTooLargeError`` before anything is
decoded: a 388 KB PNG can claim 20000 x 20000 pixels (1.2 GB as RGB). PNG, JPEG, BMP and WebP
sizes are read from the header; other codecs (TIFF) are checked right after decoding.
"""

from __future__ import annotations

import math
import operator
import os
import struct
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from pair_vpr_ros.errors import ImageConversionError, ImageTooLargeError


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
_CODECS = ("jpeg", "jpg", "png", "tiff", "webp", "bmp")
# Image files in folders (map build sources, datasets), matched case-insensitively.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_DEPTH_HEADER = 12  # compressed_depth_image_transport ConfigHeader: int32 format, float32 quant[2]
_SAMPLES = 16384  # pixels used to estimate the scaling percentiles
MAX_PIXELS = 50_000_000  # default size limit (width * height): 8K video is 33 MP
# JPEG start-of-frame markers (they carry the image size): C0..CF except DHT, JPG and DAC.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _as_bytes(data: Any, what: str) -> np.ndarray:
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


def _check_size(value: Any, name: str, where: str) -> int:
    try:
        number = operator.index(value)
    except TypeError as err:
        raise ImageConversionError(f"{where}: {name} must be an integer, got {value!r}") from err
    if number <= 0:
        raise ImageConversionError(f"{where}: {name} must be positive")
    return number


def check_pixels(width: int, height: int, max_pixels: int, where: str) -> None:
    """ImageTooLargeError when width * height exceeds `max_pixels`."""
    if width * height > max_pixels:
        raise ImageTooLargeError(
            f"{where}: the image is {width} x {height} = {width * height:,} pixels, more than "
            f"the limit of {max_pixels:,} (max_image_pixels): skipped; raise the limit if the "
            "camera really sends images this large"
        )


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
    buf = _as_bytes(data, fields + ")")
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


def compressed_to_rgb(fmt: str, data: Any, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """``sensor_msgs/CompressedImage`` format and data -> RGB uint8 [H, W, 3]."""
    buf = _as_bytes(data, f"CompressedImage (format={fmt!r})")
    where = f"CompressedImage (format={fmt!r}, len(data)={buf.size})"
    text = str(fmt).strip().lower()
    if "compresseddepth" in text:
        return cv2.cvtColor(_decode_depth(text, buf, where, max_pixels), cv2.COLOR_GRAY2RGB)
    if not any(codec in text for codec in _CODECS):
        raise ImageConversionError(
            f"{where}: unsupported format; supported: {', '.join(_CODECS)}, "
            "'<enc>; jpeg compressed bgr8' and '<16UC1|32FC1>; compressedDepth png'"
        )
    image = _imdecode(buf, where, max_pixels)
    try:
        return _decoded_to_rgb(image, where)
    except cv2.error as err:
        raise ImageConversionError(f"{where}: OpenCV could not convert it ({err})") from err


def encoded_size(buf: np.ndarray) -> tuple[int, int] | None:
    """(width, height) from the header of a PNG, JPEG, BMP or WebP [L] uint8; None otherwise."""
    head = buf[:32].tobytes()
    if head.startswith(_PNG_MAGIC) and head[12:16] == b"IHDR" and len(head) >= 24:
        return struct.unpack(">II", head[16:24])
    if head.startswith(b"BM") and len(head) >= 26:
        width, height = struct.unpack("<ii", head[18:26])
        return abs(width), abs(height)
    if head.startswith(b"RIFF") and head[8:12] == b"WEBP" and len(head) >= 30:
        chunk = head[12:16]
        if chunk == b"VP8X":  # 24-bit canvas width - 1, height - 1
            width, height = (int.from_bytes(head[a : a + 3], "little") for a in (24, 27))
            return 1 + width, 1 + height
        if chunk == b"VP8L":  # 14-bit width - 1, height - 1 after a signature byte
            bits = int.from_bytes(head[21:25], "little")
            return 1 + (bits & 0x3FFF), 1 + ((bits >> 14) & 0x3FFF)
        if chunk == b"VP8 ":
            w, h = struct.unpack("<HH", head[26:30])
            return w & 0x3FFF, h & 0x3FFF
    if head.startswith(b"\xff\xd8"):
        return _jpeg_size(buf)
    return None


def _jpeg_size(buf: np.ndarray) -> tuple[int, int] | None:
    """Walk the JPEG marker segments to the start-of-frame that holds the size."""
    pos, n = 2, buf.size
    while pos + 9 <= n:
        if buf[pos] != 0xFF:
            return None
        marker = int(buf[pos + 1])
        if marker == 0xFF:  # fill byte
            pos += 1
        elif marker in _JPEG_SOF:
            height = int(buf[pos + 5]) << 8 | int(buf[pos + 6])
            width = int(buf[pos + 7]) << 8 | int(buf[pos + 8])
            return width, height
        elif marker == 0x01 or 0xD0 <= marker <= 0xD8:  # segments without a length
            pos += 2
        else:
            pos += 2 + (int(buf[pos + 2]) << 8 | int(buf[pos + 3]))
    return None


def _imdecode(buf: np.ndarray, where: str, max_pixels: int) -> np.ndarray:
    """Encoded bytes [L] -> OpenCV image [H, W] or [H, W, C] (BGR order), any depth."""
    if buf.size == 0:
        raise ImageConversionError(f"{where}: data is empty")
    size = encoded_size(buf)
    if size is not None:
        check_pixels(*size, max_pixels, where)
    try:
        image = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except cv2.error as err:
        raise ImageConversionError(f"{where}: OpenCV could not decode it ({err})") from err
    if image is None:
        raise ImageConversionError(
            f"{where}: OpenCV could not decode the data (corrupt, truncated or not an image)"
        )
    check_pixels(image.shape[1], image.shape[0], max_pixels, where)  # codecs without a probe
    return image


def _decoded_to_rgb(image: np.ndarray, where: str) -> np.ndarray:
    """Decoded image [H, W] or [H, W, 3|4] (BGR(A); uint8, uint16 or float32) -> RGB uint8."""
    channels = 1 if image.ndim == 2 else image.shape[2]
    if channels == 1 and image.dtype in (np.uint16, np.float32):
        return cv2.cvtColor(scale_to_uint8(image.reshape(image.shape[:2])), cv2.COLOR_GRAY2RGB)
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    codes = {1: cv2.COLOR_GRAY2RGB, 3: cv2.COLOR_BGR2RGB, 4: cv2.COLOR_BGRA2RGB}
    if image.dtype != np.uint8 or channels not in codes:
        raise ImageConversionError(
            f"{where}: decoded to {channels} channel(s) of {image.dtype}; supported: 1, 3 or 4 "
            "channels of uint8 or uint16, or 1 channel of float32"
        )
    return cv2.cvtColor(
        image.reshape(image.shape[:2]) if channels == 1 else image, codes[channels]
    )


def _decode_depth(text: str, buf: np.ndarray, where: str, max_pixels: int) -> np.ndarray:
    """compressedDepth payload (12-byte header + 16-bit PNG) -> scaled grey uint8 [H, W]."""
    if "rvl" in text:  # older publishers name no codec at all: those are PNG
        raise ImageConversionError(
            f"{where}: only PNG compressedDepth is supported (not RVL); set the publisher's "
            "compressed_depth_image_transport format parameter to 'png'"
        )
    depth_enc = text.split(";")[0].strip()
    if depth_enc not in ("16uc1", "32fc1"):
        raise ImageConversionError(
            f"{where}: compressedDepth encoding {depth_enc!r} is not supported; use 16UC1 or 32FC1"
        )
    if buf[_DEPTH_HEADER : _DEPTH_HEADER + 8].tobytes() != _PNG_MAGIC:
        raise ImageConversionError(
            f"{where}: no PNG after the {_DEPTH_HEADER}-byte compressedDepth header"
        )
    image = _imdecode(buf[_DEPTH_HEADER:], where, max_pixels)
    if image.ndim != 2 or image.dtype != np.uint16:
        raise ImageConversionError(
            f"{where}: compressedDepth PNG decoded to shape {image.shape} {image.dtype}, "
            "expected one channel of uint16"
        )
    if depth_enc == "32fc1":
        # The PNG holds quantised inverse depth q = A / depth + B (0 = no reading).
        quant_a, quant_b = np.frombuffer(buf[4:_DEPTH_HEADER].tobytes(), dtype="<f4")
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            depth = np.float32(quant_a) / (image.astype(np.float32) - np.float32(quant_b))
        depth[image == 0] = np.nan
        return scale_to_uint8(depth)
    return scale_to_uint8(image)


def msg_to_rgb(msg: Any, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """An Image (has ``.encoding``) or CompressedImage (has ``.format``) -> RGB uint8 [H, W, 3].

    Works with rclpy messages (``data`` as ``array.array``, bytes or list) and rosbags messages
    (``data`` as a uint8 numpy array). Larger than `max_pixels`: ImageTooLargeError.
    """
    kind = type(msg).__name__
    try:
        if hasattr(msg, "encoding"):
            fields = (msg.encoding, msg.height, msg.width, msg.step, msg.data)
            big = bool(getattr(msg, "is_bigendian", False))
            return image_to_rgb(*fields, is_bigendian=big, max_pixels=max_pixels)
        if hasattr(msg, "format"):
            fmt, data = msg.format, msg.data
            return compressed_to_rgb(fmt, data, max_pixels=max_pixels)
    except AttributeError as err:
        raise ImageConversionError(f"{kind} message lacks a field: {err}") from err
    raise ImageConversionError(
        f"{kind} is neither a sensor_msgs/Image (no .encoding) nor a CompressedImage (no .format)"
    )


def file_to_rgb(path: str | os.PathLike, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """An image file (any codec OpenCV reads) -> RGB uint8 [H, W, 3], decoded like a
    CompressedImage (size limit, 16-bit grey scaled)."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as err:
        raise ImageConversionError(f"image file {path}: cannot read it ({err})") from err
    where = f"image file {path}"
    image = _imdecode(data, where, max_pixels)
    try:
        return _decoded_to_rgb(image, where)
    except cv2.error as err:
        raise ImageConversionError(f"{where}: OpenCV could not convert it ({err})") from err
