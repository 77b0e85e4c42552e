"""Bad-input matrix, images: every raw encoding with a wrong size, step or data length, and
compressed payloads that are truncated, garbage or claim more pixels than the limit, each give
an ImageConversionError naming the problem (the node and the replay count and skip those)."""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from pair_vpr_ros.errors import ImageConversionError, ImageTooLargeError
from pair_vpr_ros.images.encoded import compressed_to_rgb, encoded_size, file_to_rgb
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.images.raw import SUPPORTED_ENCODINGS, image_to_rgb

H, W = 8, 12  # even, so every encoding (4:2:0 YUV too) accepts the shape
BYTES_PER_PIXEL = {"8": 1, "16": 2}


def layout(encoding: str) -> tuple[int, int]:
    """(bytes per pixel in a row, rows in the buffer) of a raw encoding, from its name."""
    enc = encoding.lower()
    if enc in ("uyvy", "yuv422", "yuyv", "yuv422_yuy2"):
        return 2, H
    if enc in ("nv21", "nv12"):
        return 1, H * 3 // 2
    if enc == "32fc1":
        return 4, H
    if enc.startswith("bayer_"):
        return BYTES_PER_PIXEL[enc[10:]], H
    if enc[0].isdigit():  # 8UC3, 16UC1, ...
        depth, channels = enc.split("uc")
        return BYTES_PER_PIXEL[depth] * int(channels), H
    channels = 1 if enc.startswith("mono") else len(enc.rstrip("0123456789"))
    return channels * BYTES_PER_PIXEL[enc[len(enc.rstrip("0123456789")) :]], H


@pytest.mark.parametrize("encoding", SUPPORTED_ENCODINGS)
def test_data_one_byte_short(encoding: str) -> None:
    bpp, rows = layout(encoding)
    need = W * bpp * rows
    image_to_rgb(encoding, H, W, W * bpp, bytes(need))  # the exact length is fine
    message = f"data too short, need at least step * ({rows} - 1) + width * {bpp} = {need} bytes"
    with pytest.raises(ImageConversionError, match=re.escape(message)):
        image_to_rgb(encoding, H, W, W * bpp, bytes(need - 1))


@pytest.mark.parametrize("encoding", SUPPORTED_ENCODINGS)
def test_step_smaller_than_a_row(encoding: str) -> None:
    bpp, rows = layout(encoding)
    message = f"step is smaller than width * {bpp} bytes per pixel = {W * bpp}"
    with pytest.raises(ImageConversionError, match=re.escape(message)):
        image_to_rgb(encoding, H, W, W * bpp - 1, bytes(W * bpp * rows))


@pytest.mark.parametrize("encoding", SUPPORTED_ENCODINGS)
def test_more_pixels_than_the_limit(encoding: str) -> None:
    bpp, rows = layout(encoding)
    data = bytes(W * bpp * rows)
    assert image_to_rgb(encoding, H, W, W * bpp, data, max_pixels=H * W).shape == (H, W, 3)
    message = f"the image is {W} x {H} = {W * H} pixels, more than the limit of {W * H - 1}"
    with pytest.raises(ImageTooLargeError, match=re.escape(message)):
        image_to_rgb(encoding, H, W, W * bpp, data, max_pixels=H * W - 1)


@pytest.mark.parametrize("encoding", SUPPORTED_ENCODINGS)
def test_huge_claimed_size_with_little_data(encoding: str) -> None:
    bpp, _ = layout(encoding)
    message = "the image is 20000 x 20000 = 400,000,000 pixels, more than the limit of 50,000,000"
    with pytest.raises(ImageTooLargeError, match=re.escape(message)):
        image_to_rgb(encoding, 20000, 20000, 20000 * bpp, bytes(100))


# ---- compressed payloads

GRADIENT = np.stack(np.broadcast_arrays(*np.ogrid[0:48, 0:64], 100)[::-1], axis=-1).astype(
    np.uint8
)


def encode(ext: str, image: np.ndarray = GRADIENT) -> bytes:
    ok, buf = cv2.imencode(ext, image)
    assert ok
    return buf.tobytes()


def png_claiming(width: int, height: int) -> bytes:
    """A small real PNG whose IHDR (CRC fixed) claims width x height: what a decoder trusts."""
    data = bytearray(encode(".png"))
    data[16:24] = struct.pack(">II", width, height)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    return bytes(data)


def jpeg_claiming(width: int, height: int) -> bytes:
    data = bytearray(encode(".jpg"))
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def bmp_claiming(width: int, height: int) -> bytes:
    data = bytearray(encode(".bmp"))
    data[18:26] = struct.pack("<ii", width, -height)  # top-down rows: negative height
    return bytes(data)


def webp_claiming(width: int, height: int) -> bytes:
    """An extended-format (VP8X) WebP header claiming a width x height canvas."""
    body = b"VP8X" + struct.pack("<I", 10) + b"\0" * 4
    body += (width - 1).to_bytes(3, "little") + (height - 1).to_bytes(3, "little")
    return b"RIFF" + struct.pack("<I", 4 + len(body)) + b"WEBP" + body


def depth_claiming(width: int, height: int) -> bytes:
    png = bytearray(encode(".png", np.zeros((4, 4), np.uint16)))
    png[16:24] = struct.pack(">II", width, height)
    png[29:33] = struct.pack(">I", zlib.crc32(bytes(png[12:29])))
    return b"\0" * 12 + bytes(png)


def truncated(ext: str, fraction: float) -> bytes:
    data = encode(ext)
    return data[: int(len(data) * fraction)]


UNDECODABLE = "OpenCV could not decode the data (corrupt, truncated or not an image)"
TOO_LARGE = "the image is 20000 x 20000 = 400,000,000 pixels, more than the limit of 50,000,000"
COMPRESSED = {
    **{
        f"{ext[1:]} cut at {int(f * 100)}%": (
            "png" if ext == ".png" else ext[1:],
            truncated(ext, f),
        )
        for ext in (".png", ".jpg", ".webp", ".bmp", ".tiff")
        for f in (0.25, 0.9)
    },
    "png header only": ("png", encode(".png")[:33]),
    "jpeg markers only": ("jpeg", b"\xff\xd8\xff\xd9"),
    "random bytes": ("jpeg", np.random.default_rng(0).integers(0, 256, 500, np.uint8).tobytes()),
    "text": ("png", b"definitely not an image"),
    "png 20000x20000": ("png", png_claiming(20000, 20000)),
    "jpeg 20000x20000": ("jpeg", jpeg_claiming(20000, 20000)),
    "bmp 20000x20000": ("bmp", bmp_claiming(20000, 20000)),
    "webp 20000x20000": ("webp", webp_claiming(20000, 20000)),
    "depth 20000x20000": ("16UC1; compressedDepth png", depth_claiming(20000, 20000)),
    "jpeg format, png 20000x20000": ("bgr8; jpeg compressed bgr8", png_claiming(20000, 20000)),
}
EXPECTED = {
    **{name: (ImageConversionError, UNDECODABLE) for name in COMPRESSED},
    **{name: (ImageTooLargeError, TOO_LARGE) for name in COMPRESSED if "20000" in name},
}


@pytest.mark.parametrize("case", list(COMPRESSED))
def test_bad_compressed_payload(case: str) -> None:
    fmt, data = COMPRESSED[case]
    error, message = EXPECTED[case]
    with pytest.raises(error, match=re.escape(message)):
        compressed_to_rgb(fmt, data)


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".webp"])
def test_header_sizes_are_read_without_decoding(ext: str) -> None:
    assert encoded_size(np.frombuffer(encode(ext), np.uint8)) == (64, 48)


def test_codec_without_a_probe_is_checked_after_decoding() -> None:
    tiff = encode(".tiff")
    assert encoded_size(np.frombuffer(tiff, np.uint8)) is None
    assert compressed_to_rgb("tiff", tiff, max_pixels=64 * 48).shape == (48, 64, 3)
    with pytest.raises(ImageTooLargeError, match="64 x 48 = 3,072 pixels, more than the limit"):
        compressed_to_rgb("tiff", tiff, max_pixels=64 * 48 - 1)


def test_limit_is_configurable_and_default() -> None:
    png = encode(".png")
    assert MAX_PIXELS == 50_000_000
    np.testing.assert_array_equal(compressed_to_rgb("png", png), GRADIENT[..., ::-1])
    with pytest.raises(ImageTooLargeError, match="limit of 3,071 \\(max_image_pixels\\)"):
        compressed_to_rgb("png", png, max_pixels=3071)


@pytest.mark.parametrize(
    ("name", "content", "error", "message"),
    [
        ("missing.png", None, ImageConversionError, "cannot read it"),
        ("empty.png", b"", ImageConversionError, "data is empty"),
        ("text.png", b"hello", ImageConversionError, UNDECODABLE),
        ("huge.png", png_claiming(20000, 20000), ImageTooLargeError, TOO_LARGE),
    ],
)
def test_bad_image_files(tmp_path: Path, name, content, error, message) -> None:
    if content is not None:
        (tmp_path / name).write_bytes(content)
    with pytest.raises(error, match=re.escape(message)):
        file_to_rgb(tmp_path / name)


@pytest.mark.parametrize("shape", [(1, 20000), (20000, 1), (2, 5000), (1, 641)])
@pytest.mark.parametrize("kind", ["sift", "orb"])
def test_extreme_aspect_ratio_gives_features_not_a_cv2_error(shape, kind) -> None:
    """Issue 25: a 1 x 20000 image scaled to max_side 640 had a height of 0 (cv2 `!dsize.empty()`
    in resize); each side now keeps at least one pixel, keypoints stay in full-size pixels."""
    from pair_vpr_ros.geometry.features import extract_features

    rgb = np.random.default_rng(0).integers(0, 256, (*shape, 3), dtype=np.uint8)
    out = extract_features(rgb, kind=kind)
    assert out.kind == kind and out.keypoints.shape[1] == 2
    assert len(out.keypoints) == len(out.descriptors)
    if len(out.keypoints):
        assert (out.keypoints >= 0).all()
        assert (out.keypoints[:, 0] < shape[1]).all() and (out.keypoints[:, 1] < shape[0]).all()
