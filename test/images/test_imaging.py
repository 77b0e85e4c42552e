"""Tests for pair_vpr_ros.images.convert: encodings vs a reference, padding, byte order, errors."""

from __future__ import annotations

import array
import re
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from pair_vpr_ros.errors import ImageConversionError
from pair_vpr_ros.images.convert import msg_to_rgb
from pair_vpr_ros.images.encoded import compressed_to_rgb
from pair_vpr_ros.images.pixels import scale_to_uint8
from pair_vpr_ros.images.raw import SUPPORTED_ENCODINGS, image_to_rgb

pytestmark = pytest.mark.filterwarnings("error")  # e.g. NaN cast to uint8 would only warn

H, W = 48, 64


def make_reference() -> np.ndarray:
    """RGB uint8 [48, 64, 3]: smooth gradients plus sharp shapes aligned to 2x2 blocks."""
    yy, xx = np.mgrid[0:H, 0:W]
    ref = np.stack([xx * 4 % 256, yy * 5, 255 - (xx + yy) * 2], axis=-1).astype(np.uint8)
    ref[8:20, 10:24] = (250, 20, 30)
    ref[26:40, 36:58] = (10, 200, 60)
    ref[30:34, 4:30] = (255, 255, 255)
    return ref


REF = make_reference()
GREY = cv2.cvtColor(REF, cv2.COLOR_RGB2GRAY)
RNG = np.random.default_rng(7)
NOISE = RNG.integers(0, 256, (H, W, 4), dtype=np.uint16)  # low bytes that >> 8 must drop


def near_edges(ref: np.ndarray, radius: int = 2) -> np.ndarray:
    """Pixels within `radius` of a jump > 20 between neighbours: bool [H, W]."""
    r = ref.astype(int)
    jump = np.zeros(ref.shape[:2], np.uint8)
    jump[:, 1:] |= np.abs(r[:, 1:] - r[:, :-1]).max(-1) > 20
    jump[1:, :] |= np.abs(r[1:] - r[:-1]).max(-1) > 20
    return cv2.dilate(jump, np.ones((2 * radius + 1,) * 2, np.uint8)).astype(bool)


NEAR_EDGES = near_edges(REF)
BAYER_SITES = {"rggb": "RGGB", "bggr": "BGGR", "gbrg": "GBRG", "grbg": "GRBG"}


def mosaic(pattern: str) -> np.ndarray:
    """Sample REF through a Bayer colour-filter array: [H, W] uint8."""
    out = np.zeros((H, W), np.uint8)
    for k, colour in enumerate(BAYER_SITES[pattern]):
        dy, dx = divmod(k, 2)
        out[dy::2, dx::2] = REF[dy::2, dx::2, "RGB".index(colour)]
    return out


def nv_planes(order: str) -> np.ndarray:
    """REF as NV21 (order "vu") or NV12 ("uv"): [H * 3 / 2, W] uint8."""
    i420 = cv2.cvtColor(REF, cv2.COLOR_RGB2YUV_I420)
    u = i420[H : H + H // 4].reshape(H // 2, W // 2)
    v = i420[H + H // 4 :].reshape(H // 2, W // 2)
    chroma = np.stack([v, u] if order == "vu" else [u, v], axis=-1).reshape(H // 2, W)
    return np.concatenate([i420[:H], chroma])


def raw_rows(encoding: str) -> tuple[np.ndarray, np.ndarray, int]:
    """(buffer rows [rows, row_bytes] uint8, expected RGB [H, W, 3], max abs error allowed).

    Lossy encodings (Bayer, YUV) are held to their bound away from the sharp edges only.
    """
    enc = encoding.lower()
    alpha = RNG.integers(0, 256, (H, W, 1), dtype=np.uint8)
    grey3 = np.repeat(GREY[..., None], 3, axis=-1)
    eight = {
        "rgb8": REF,
        "bgr8": REF[..., ::-1],
        "8uc3": REF[..., ::-1],
        "rgba8": np.concatenate([REF, alpha], -1),
        "bgra8": np.concatenate([REF[..., ::-1], alpha], -1),
        "8uc4": np.concatenate([REF[..., ::-1], alpha], -1),
    }
    if enc in eight:
        return eight[enc].reshape(H, -1), REF, 0
    if enc in ("mono8", "8uc1"):
        return GREY, grey3, 0
    if enc.rstrip("16") in ("rgb", "bgr", "rgba", "bgra") or enc in ("16uc3", "16uc4"):
        base = enc.replace("16uc3", "bgr").replace("16uc4", "bgra").rstrip("16")
        samples = eight[base + "8"].astype(np.uint16) << 8 | NOISE[..., : len(base)]
        return samples.astype("<u2").view(np.uint8).reshape(H, -1), REF, 0
    if enc.startswith("bayer_"):
        cfa = mosaic(enc[6:10])
        if enc.endswith("16"):
            cfa16 = cfa.astype(np.uint16) * 257
            return cfa16.astype("<u2").view(np.uint8).reshape(H, -1), REF, 6
        return cfa, REF, 6
    if enc in ("uyvy", "yuv422"):
        return cv2.cvtColor(REF, cv2.COLOR_RGB2YUV_UYVY).reshape(H, -1), REF, 3
    if enc in ("yuyv", "yuv422_yuy2"):
        return cv2.cvtColor(REF, cv2.COLOR_RGB2YUV_YUY2).reshape(H, -1), REF, 3
    if enc in ("nv21", "nv12"):
        return nv_planes("vu" if enc == "nv21" else "uv"), REF, 10
    raise AssertionError(f"no test data for {encoding}")


SCALED = {"mono16", "16uc1", "32fc1"}  # contrast-stretched: see the scaling tests below
RAW_ENCODINGS = [e for e in SUPPORTED_ENCODINGS if e.lower() not in SCALED]


def padded(rows: np.ndarray, pad: int) -> tuple[bytes, int]:
    """Append `pad` garbage bytes to every row: (data, step)."""
    junk = np.full((rows.shape[0], pad), 0xAB, np.uint8)
    return np.concatenate([rows, junk], axis=1).tobytes(), rows.shape[1] + pad


@pytest.mark.parametrize("encoding", RAW_ENCODINGS)
def test_encoding_matches_reference(encoding: str) -> None:
    rows, expected, tol = raw_rows(encoding)
    out = image_to_rgb(encoding, H, W, rows.shape[1], rows.tobytes())
    assert out.shape == (H, W, 3) and out.dtype == np.uint8 and out.flags.c_contiguous
    diff = np.abs(out.astype(int) - expected)
    if tol == 0:
        assert diff.max() == 0
    else:  # demosaicing and chroma subsampling blur the sharp edges; a wrong layout gives > 60
        assert diff[~NEAR_EDGES].max() <= tol
        assert diff.mean() < 4.0


@pytest.mark.parametrize("encoding", [*RAW_ENCODINGS, "mono16", "16UC1", "32FC1"])
@pytest.mark.parametrize("pad", [1, 7])
def test_padded_rows_give_identical_result(encoding: str, pad: int) -> None:
    if encoding == "32FC1":
        rows = (GREY.astype("<f4") / 7.0).view(np.uint8).reshape(H, -1)
    else:
        rows = mono16_rows() if encoding.lower() in SCALED else raw_rows(encoding)[0]
    data, step = padded(rows, pad)
    tight = image_to_rgb(encoding, H, W, rows.shape[1], rows.tobytes())
    np.testing.assert_array_equal(image_to_rgb(encoding, H, W, step, data), tight)


def mono16_rows(order: str = "<") -> np.ndarray:
    values = 1000 + GREY.astype(np.uint16) * 40
    return values.astype(order + "u2").view(np.uint8).reshape(H, -1)


@pytest.mark.parametrize("encoding", ["mono16", "16UC1", "rgb16", "bgra16", "bayer_gbrg16"])
def test_big_endian_equals_little_endian(encoding: str) -> None:
    rows = mono16_rows() if encoding.lower() in SCALED else raw_rows(encoding)[0]
    little = image_to_rgb(encoding, H, W, rows.shape[1], rows.tobytes())
    swapped = rows.view("<u2").astype(">u2").view(np.uint8)
    big = image_to_rgb(encoding, H, W, rows.shape[1], swapped.tobytes(), is_bigendian=True)
    np.testing.assert_array_equal(big, little)
    assert little.std() > 10  # not a trivially black image


def expected_scaled(values: np.ndarray) -> np.ndarray:
    """The documented mapping for images of <= 16k pixels (the subsample is the whole image)."""
    finite = values[np.isfinite(values)].astype(np.float64)
    lo, hi = np.percentile(finite, [1.0, 99.0])
    out = np.clip(np.floor((values.astype(np.float64) - lo) * 255.0 / (hi - lo) + 0.5), 0, 255)
    return np.where(np.isfinite(values), out, 0).astype(np.uint8)


def test_mono16_robust_scaling_ignores_hot_pixels() -> None:
    values = (1000 + GREY.astype(np.uint16) * 40).astype("<u2")
    values[0, :5] = 65535  # hot pixels must not compress the rest into a few grey levels
    out = image_to_rgb("mono16", H, W, W * 2, values.tobytes())
    assert (out[..., 0] == out[..., 1]).all() and (out[..., 0] == out[..., 2]).all()
    assert np.abs(out[..., 0].astype(int) - expected_scaled(values)).max() <= 1
    assert out[..., 0].min() == 0 and out[..., 0].max() == 255
    assert (out[0, :5] == 255).all()


def test_32fc1_ignores_nan_and_inf() -> None:
    depth = (0.5 + GREY.astype(np.float32) / 25.0).astype("<f4")
    depth[5, :10] = np.nan
    depth[6, :3] = np.inf
    depth[7, :3] = -np.inf
    depth[8, :2] = (3e38, -3e38)  # finite outliers saturate (and overflow float32 when scaled)
    out = image_to_rgb("32FC1", H, W, W * 4, depth.tobytes())[..., 0]
    assert np.abs(out.astype(int) - expected_scaled(depth)).max() <= 1
    assert (out[5, :10] == 0).all() and (out[6:8, :3] == 0).all()
    assert out[8, :2].tolist() == [255, 0]
    big = depth.astype(">f4").tobytes()
    np.testing.assert_array_equal(image_to_rgb("32FC1", H, W, W * 4, big, True)[..., 0], out)


def test_scaling_constant_and_degenerate_images() -> None:
    assert not scale_to_uint8(np.full((H, W), 1234, np.uint16)).any()
    assert not scale_to_uint8(np.full((H, W), np.nan, np.float32)).any()
    sparse = np.zeros((H, W), np.uint16)
    sparse[:2, :3] = 500  # < 1 % of the pixels: percentiles are equal, min..max is used
    sparse[2, :3] = 250
    out = scale_to_uint8(sparse)
    assert (out[:2, :3] == 255).all() and (out[2, :3] == 128).all()
    assert out.sum() == 6 * 255 + 3 * 128


@pytest.mark.parametrize(
    "wrap",
    [bytes, bytearray, lambda b: array.array("B", b), lambda b: np.frombuffer(b, np.uint8), list],
    ids=["bytes", "bytearray", "array", "numpy", "list"],
)
def test_msg_to_rgb_accepts_every_data_container(wrap) -> None:
    rows, _, _ = raw_rows("bgr8")
    data, step = padded(rows, 4)
    msg = SimpleNamespace(
        encoding="bgr8", height=H, width=W, step=step, is_bigendian=0, data=wrap(data)
    )
    np.testing.assert_array_equal(msg_to_rgb(msg), REF)
    ok, png = cv2.imencode(".png", REF[..., ::-1])
    assert ok
    np.testing.assert_array_equal(msg_to_rgb(SimpleNamespace(format="png", data=wrap(png))), REF)


def test_result_never_aliases_message_memory() -> None:
    data = np.ascontiguousarray(REF).reshape(-1).copy()
    out = image_to_rgb("rgb8", H, W, W * 3, data)
    out[:] = 0
    assert data.any()


def depth_payload(png: np.ndarray, quant: tuple[float, float] = (0.0, 0.0)) -> bytes:
    header = np.array([0], "<i4").tobytes() + np.array(quant, "<f4").tobytes()
    return header + png.tobytes()


def encode(ext: str, image: np.ndarray, *params: int) -> np.ndarray:
    ok, buf = cv2.imencode(ext, image, list(params))
    assert ok
    return buf


@pytest.mark.parametrize(
    "fmt", ["jpeg", "jpg", "bgr8; jpeg compressed bgr8", "rgb8; jpeg compressed bgr8"]
)
def test_compressed_jpeg(fmt: str) -> None:
    jpg = encode(".jpg", REF[..., ::-1], cv2.IMWRITE_JPEG_QUALITY, 95)
    diff = np.abs(compressed_to_rgb(fmt, jpg.tobytes()).astype(int) - REF)
    assert diff.mean() < 5.0 and diff[~NEAR_EDGES].max() <= 12  # BGR read as RGB gives > 60


def test_compressed_png_variants() -> None:
    np.testing.assert_array_equal(compressed_to_rgb("png", encode(".png", REF[..., ::-1])), REF)
    grey = compressed_to_rgb("mono8; png compressed mono8", encode(".png", GREY))
    np.testing.assert_array_equal(grey, np.repeat(GREY[..., None], 3, -1))
    bgra = np.concatenate([REF[..., ::-1], np.zeros((H, W, 1), np.uint8)], -1)
    np.testing.assert_array_equal(compressed_to_rgb("png", encode(".png", bgra)), REF)
    colour16 = REF[..., ::-1].astype(np.uint16) << 8 | NOISE[..., :3]
    np.testing.assert_array_equal(compressed_to_rgb("png", encode(".png", colour16)), REF)
    mono16 = mono16_rows().view("<u2").reshape(H, W)
    expected = image_to_rgb("mono16", H, W, W * 2, mono16.tobytes())
    assert expected.std() > 10
    np.testing.assert_array_equal(compressed_to_rgb("png", encode(".png", mono16)), expected)


def test_compressed_depth_16uc1() -> None:
    depth = mono16_rows().view("<u2").reshape(H, W)
    payload = depth_payload(encode(".png", depth))
    expected = image_to_rgb("16UC1", H, W, W * 2, depth.tobytes())
    np.testing.assert_array_equal(
        compressed_to_rgb("16UC1; compressedDepth png", payload), expected
    )
    np.testing.assert_array_equal(compressed_to_rgb("16UC1; compressedDepth", payload), expected)


def test_compressed_depth_32fc1_recovers_depth() -> None:
    depth = (0.5 + GREY.astype(np.float32) / 30.0).astype(np.float32)  # metres, < 9.5
    depth[:3, :4] = np.nan
    q = 100.0  # compressed_depth_image_transport: A = q (q + 1), B = 1 - A / depth_max
    quant_a, quant_b = q * (q + 1.0), 1.0 - q * (q + 1.0) / 10.0
    inverse = np.nan_to_num(np.rint(quant_a / depth + quant_b), nan=0.0).astype(np.uint16)
    payload = depth_payload(encode(".png", inverse), (quant_a, quant_b))
    out = compressed_to_rgb("32FC1; compressedDepth png", payload)
    expected = image_to_rgb("32FC1", H, W, W * 4, depth.tobytes())
    assert np.abs(out.astype(int) - expected).max() <= 2  # depth, not inverse depth
    assert (out[:3, :4] == 0).all()


SIZES = f"height={H}, width={W}"


@pytest.mark.parametrize(
    ("encoding", "height", "width", "step", "length", "message"),
    [
        ("rgb9", H, W, W * 3, H * W * 3, "unsupported encoding; supported: rgb8, bgr8"),
        ("rgb8", 0, W, W * 3, 10, "height must be positive"),
        ("rgb8", H, -2, W * 3, 10, "width must be positive"),
        ("rgb8", H, W, 0, 10, "step must be positive"),
        ("rgb8", H, W, 100, H * 100, "step is smaller than width * 3 bytes per pixel = 192"),
        ("mono16", H, W, 127, H * W * 2, "step is smaller than width * 2 bytes per pixel = 128"),
        (
            "rgb8",
            H,
            W,
            200,
            200 * 47 + 191,
            f"Image (encoding='rgb8', {SIZES}, step=200, len(data)=9591): data too short, "
            "need at least step * (48 - 1) + width * 3 = 9592 bytes",
        ),
        ("nv21", H, W, W, H * W, "need at least step * (72 - 1) + width * 1 = 4608 bytes"),
        ("uyvy", H, W - 1, W * 2, H * W * 2, "width must be even for 4:2:2 YUV"),
        ("nv21", H - 1, W, W, H * W * 2, "height and width must be even for 4:2:0 YUV"),
        ("nv12", H, W - 1, W, H * W * 2, "height and width must be even for 4:2:0 YUV"),
    ],
)
def test_malformed_image_raises(encoding, height, width, step, length, message) -> None:
    with pytest.raises(ImageConversionError, match=re.escape(message)):
        image_to_rgb(encoding, height, width, step, bytes(length))


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (np.zeros(10, np.float64), "step=3): data must be uint8, got dtype float64"),
        ([1, 2, 300], "data is not a byte buffer"),
        (None, "data must be bytes, array.array, a list of ints or a uint8 numpy array"),
    ],
)
def test_bad_data_container_raises(data, message) -> None:
    with pytest.raises(ImageConversionError, match=re.escape(message)):
        image_to_rgb("mono8", 1, 3, 3, data)


def test_non_integer_size_raises() -> None:
    with pytest.raises(ImageConversionError, match="height must be an integer, got 'a'"):
        image_to_rgb("mono8", "a", 3, 3, bytes(9))


@pytest.mark.parametrize(
    ("fmt", "data", "message"),
    [
        ("jpeg", b"", "CompressedImage (format='jpeg', len(data)=0): data is empty"),
        ("jpeg", b"not an image at all", "could not decode the data (corrupt, truncated"),
        ("h264", b"\x00\x01", "unsupported format; supported: jpeg, jpg, png"),
        ("16UC1; compressedDepth rvl", b"x" * 20, "only PNG compressedDepth is supported"),
        ("mono8; compressedDepth png", b"x" * 20, "compressedDepth encoding 'mono8' is not"),
    ],
)
def test_malformed_compressed_raises(fmt: str, data: bytes, message: str) -> None:
    with pytest.raises(ImageConversionError, match=re.escape(message)):
        compressed_to_rgb(fmt, data)


def test_malformed_compressed_depth_raises() -> None:
    png16 = encode(".png", np.zeros((4, 4), np.uint16)).tobytes()
    with pytest.raises(ImageConversionError, match="no PNG after the 12-byte compressedDepth"):
        compressed_to_rgb("16UC1; compressedDepth png", png16)
    png8 = depth_payload(encode(".png", np.zeros((4, 4), np.uint8)))
    with pytest.raises(ImageConversionError, match=re.escape("expected one channel of uint16")):
        compressed_to_rgb("16UC1; compressedDepth png", png8)


def test_unsupported_decoded_layout_raises() -> None:
    tiff = encode(".tiff", np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ImageConversionError, match=r"decoded to 3 channel\(s\) of float32"):
        compressed_to_rgb("tiff", tiff)


def test_opencv_errors_are_wrapped(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(*_args, **_kwargs):
        raise cv2.error("simulated failure")

    monkeypatch.setattr(cv2, "cvtColor", broken)
    with pytest.raises(ImageConversionError, match="OpenCV could not convert it") as info:
        image_to_rgb("bgr8", 2, 2, 6, bytes(12))
    assert isinstance(info.value.__cause__, cv2.error)
    with pytest.raises(ImageConversionError, match="OpenCV could not convert it"):
        compressed_to_rgb("png", encode(".png", REF))


def test_msg_to_rgb_rejects_other_messages() -> None:
    with pytest.raises(ImageConversionError, match="SimpleNamespace is neither a sensor_msgs"):
        msg_to_rgb(SimpleNamespace(data=b""))
    with pytest.raises(ImageConversionError, match="message lacks a field: .*step"):
        msg_to_rgb(SimpleNamespace(encoding="rgb8", height=1, width=1, data=b"abc"))


def test_rosbags_messages_after_cdr_round_trip() -> None:
    typesys = pytest.importorskip("rosbags.typesys")
    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    types = store.types
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id="cam"
    )
    rows, _, _ = raw_rows("yuyv")
    data, step = padded(rows, 6)
    image_type = types["sensor_msgs/msg/Image"]
    raw = image_type(
        header=header,
        height=H,
        width=W,
        encoding="yuyv",
        is_bigendian=0,
        step=step,
        data=np.frombuffer(data, np.uint8),
    )
    name = image_type.__msgtype__
    received = store.deserialize_cdr(store.serialize_cdr(raw, name), name)
    assert isinstance(received.data, np.ndarray)
    expected = image_to_rgb("yuyv", H, W, rows.shape[1], rows.tobytes())
    np.testing.assert_array_equal(msg_to_rgb(received), expected)
    compressed_type = types["sensor_msgs/msg/CompressedImage"]
    png = compressed_type(header=header, format="png", data=encode(".png", REF[..., ::-1]))
    name = compressed_type.__msgtype__
    received = store.deserialize_cdr(store.serialize_cdr(png, name), name)
    np.testing.assert_array_equal(msg_to_rgb(received), REF)
