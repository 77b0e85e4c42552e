"""Encoded images -> RGB uint8: ``sensor_msgs/CompressedImage`` data and image files.

Formats and rules are listed in :mod:`pair_vpr_ros.images.convert`. The size limit is checked
from the PNG, JPEG, BMP or WebP header before anything is decoded (`encoded_size`), other codecs
right after decoding.
"""

from __future__ import annotations

import os
import struct
from typing import Any

import cv2
import numpy as np

from pair_vpr_ros.errors import ImageConversionError
from pair_vpr_ros.images.pixels import MAX_PIXELS, as_bytes, check_pixels, scale_to_uint8

_CODECS = ("jpeg", "jpg", "png", "tiff", "webp", "bmp")
# Image files in folders (map build sources, datasets), matched case-insensitively.
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_DEPTH_HEADER = 12  # compressed_depth_image_transport ConfigHeader: int32 format, float32 quant[2]
# JPEG start-of-frame markers (they carry the image size): C0..CF except DHT, JPG and DAC.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def compressed_to_rgb(fmt: str, data: Any, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """``sensor_msgs/CompressedImage`` format and data -> RGB uint8 [H, W, 3]."""
    buf = as_bytes(data, f"CompressedImage (format={fmt!r})")
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
