"""Camera models from CameraInfo / parameters, undistortion, packing; depth images."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from pair_vpr_ros.errors import GeometryInputError
from pair_vpr_ros.geometry import camera_from_info, camera_from_params
from pair_vpr_ros.geometry.camera import PACKED_SIZE, CameraModel
from pair_vpr_ros.geometry.depth import depth_from_msg


def info(**over):
    fields = dict(
        width=640, height=480, k=[500.0, 0, 320.0, 0, 510.0, 240.0, 0, 0, 1],
        d=[0.1, -0.05, 0.001, 0.002, 0.01], distortion_model="plumb_bob",
    )  # fmt: skip
    return SimpleNamespace(**{**fields, **over})


def test_camera_info_gives_intrinsics():
    cam = camera_from_info(info())
    assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height) == (
        500,
        510,
        320,
        240,
        640,
        480,
    )
    assert cam.distortion_model == "plumb_bob" and cam.distorted
    np.testing.assert_array_equal(cam.k, [[500, 0, 320], [0, 510, 240], [0, 0, 1]])
    plain = camera_from_info(info(d=[], distortion_model=""))
    assert plain.distortion_model == "none" and not plain.distorted


@pytest.mark.parametrize(
    ("over", "message"),
    [
        (dict(k=[0.0] * 9), "focal lengths fx=0.0, fy=0.0 must be > 0 .*not calibrated"),
        (dict(k=[-5.0, 0, 1, 0, 5.0, 1, 0, 0, 1]), "fx=-5.0, fy=5.0 must be > 0"),
        (dict(k=[1.0, 2.0]), "CameraInfo k must hold 9 values, got 2"),
        (dict(width=0), "width and height must be > 0"),
        (dict(distortion_model="kannala"), "unknown distortion model 'kannala'; supported: "),
        (dict(d=[0.1, 0.2, 0.3]), "'plumb_bob' takes 4 or 5 coefficients, got 3"),
        (dict(k=[float("nan")] + [1.0] * 8), "intrinsics must be finite numbers"),
        (dict(k="abc"), "not a CameraInfo message"),
    ],
)
def test_bad_camera_info_is_a_clear_error(over, message):
    with pytest.raises(GeometryInputError, match=message):
        camera_from_info(info(**over))


def test_parameters_give_the_same_model():
    cam = camera_from_params(640, 480, 500, 510, 320, 240, "plumb_bob", [0.1, -0.05, 0, 0, 0])
    assert cam == CameraModel(640, 480, 500.0, 510.0, 320.0, 240.0, "plumb_bob",
                              (0.1, -0.05, 0.0, 0.0, 0.0))  # fmt: skip
    assert camera_from_params(640, 480, 500, 500, 320, 240, "plumb_bob").distortion_model == "none"


def test_plumb_bob_undistortion_inverts_opencv_projection():
    cam = camera_from_info(info())
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-0.5, 0.5, (50, 2)), np.ones(50)]  # camera-frame rays
    distorted = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.k, np.array(cam.d))[0]
    ideal = (pts[:, :2] * (cam.fx, cam.fy)) + (cam.cx, cam.cy)
    np.testing.assert_allclose(cam.undistort(distorted.reshape(-1, 2)), ideal, atol=1e-3)
    np.testing.assert_allclose(cam.rays(distorted.reshape(-1, 2)), pts, atol=1e-5)


def test_equidistant_undistortion_inverts_the_fisheye_model():
    cam = camera_from_params(640, 480, 300, 300, 320, 240, "equidistant", [0.05, -0.01, 0.002, 0])
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-0.8, 0.8, (50, 2)), np.ones(50)]
    distorted = cv2.fisheye.projectPoints(
        pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.k, np.array(cam.d)
    )[0]
    np.testing.assert_allclose(cam.rays(distorted.reshape(-1, 2)), pts, atol=1e-4)


def test_pack_round_trip():
    for cam in (camera_from_info(info()), camera_from_params(320, 240, 160, 160, 159.5, 143.5)):
        data = cam.pack()
        assert len(data) == PACKED_SIZE
        assert CameraModel.unpack(data) == cam
    with pytest.raises(GeometryInputError, match="not a camera model"):
        CameraModel.unpack(b"XXXX" + cam.pack()[4:])


def depth_msg(values: np.ndarray, encoding: str, pad: int = 0, big: bool = False):
    h, w = values.shape
    dtype = np.dtype(">u2" if big else "<u2") if encoding == "16UC1" else np.dtype("<f4")
    rows = values.astype(dtype).view(np.uint8).reshape(h, -1)
    data = np.pad(rows, ((0, 0), (0, pad))).tobytes()
    return SimpleNamespace(
        encoding=encoding, height=h, width=w, step=rows.shape[1] + pad, data=data, is_bigendian=big
    )


def test_depth_images_16uc1_and_32fc1_become_metres_with_nan_for_none():
    mm = np.array([[0, 1500], [65535, 250]])
    for pad, big in ((0, False), (6, True)):
        got = depth_from_msg(depth_msg(mm, "16UC1", pad, big))
        np.testing.assert_allclose(got, [[np.nan, 1.5], [65.535, 0.25]], rtol=1e-6)
    metres = np.array([[np.nan, 1.5], [np.inf, -1.0]], np.float32)
    got = depth_from_msg(depth_msg(metres, "32FC1"))
    np.testing.assert_array_equal(np.isnan(got), [[True, False], [True, True]])
    assert got.dtype == np.float32 and got[0, 1] == 1.5


def test_bad_depth_images_are_clear_errors():
    with pytest.raises(GeometryInputError, match="encoding 'rgb8' is not supported: use 16UC1"):
        depth_from_msg(depth_msg(np.zeros((2, 2)), "16UC1").__class__(
            encoding="rgb8", height=2, width=2, step=6, data=b"\0" * 12, is_bigendian=0
        ))  # fmt: skip
    short = depth_msg(np.zeros((4, 4)), "16UC1")
    short.data = short.data[:10]
    with pytest.raises(GeometryInputError, match="depth image: .*data too short"):
        depth_from_msg(short)
