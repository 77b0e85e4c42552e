"""Camera intrinsics: from a ``sensor_msgs/CameraInfo`` or from parameters; PoseLib's model.

Pixel coordinates follow ROS / OpenCV: the centre of the top-left pixel is (0, 0). Keypoints are
stored distorted (as detected). The pose code hands them to PoseLib with the camera's own model
(`solver_camera`: camera_info's D as it is), so its RANSAC and refinement measure errors in the
image's own pixels; `rays` / `undistort` unproject through the same model.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import poselib

from pair_vpr_ros.errors import GeometryInputError

# ROS distortion model names -> number of coefficients OpenCV accepts for them.
DISTORTION_MODELS = {
    "none": (0,),
    "plumb_bob": (4, 5),  # k1 k2 t1 t2 [k3]
    "rational_polynomial": (8,),  # k1 k2 t1 t2 k3 k4 k5 k6
    "equidistant": (4,),  # k1 k2 k3 k4 (OpenCV fisheye)
}
_MODEL_CODES = {name: i for i, name in enumerate(DISTORTION_MODELS)}
_PACK = struct.Struct("<4sBB2xII6d8d")  # magic, version, model, size, fx fy cx cy (+2 spare), d
PACKED_SIZE = _PACK.size


@dataclass(frozen=True)
class CameraModel:
    """Pinhole intrinsics (pixels) of a `width` x `height` image plus ROS-style distortion."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion_model: str = "none"
    d: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        where = f"camera model {self.width}x{self.height}"
        if not (self.width > 0 and self.height > 0):
            raise GeometryInputError(f"{where}: width and height must be > 0")
        values = (self.fx, self.fy, self.cx, self.cy, *self.d)
        if not all(math.isfinite(v) for v in values):
            raise GeometryInputError(f"{where}: intrinsics must be finite numbers, got {values}")
        if self.fx <= 0 or self.fy <= 0:
            raise GeometryInputError(
                f"{where}: focal lengths fx={self.fx}, fy={self.fy} must be > 0 (an all-zero "
                "CameraInfo K means the camera is not calibrated: calibrate it or set the "
                "intrinsics parameters)"
            )
        sizes = DISTORTION_MODELS.get(self.distortion_model)
        if sizes is None:
            raise GeometryInputError(
                f"{where}: unknown distortion model {self.distortion_model!r}; supported: "
                f"{', '.join(DISTORTION_MODELS)}"
            )
        if len(self.d) not in sizes and any(self.d):
            raise GeometryInputError(
                f"{where}: distortion model {self.distortion_model!r} takes "
                f"{' or '.join(map(str, sizes))} coefficients, got {len(self.d)}"
            )

    @property
    def k(self) -> np.ndarray:
        """[3, 3] camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distorted(self) -> bool:
        return self.distortion_model != "none" and any(self.d)

    def solver_camera(self) -> poselib.Camera:
        """This camera as PoseLib's model (`solver_model`): its distortion, not an ideal one."""
        return _solver_camera(self)

    def rays(self, px: np.ndarray) -> np.ndarray:
        """Distorted pixels [N, 2] -> camera-frame directions [N, 3] with z = 1."""
        pts = np.asarray(px, np.float64).reshape(-1, 2)
        if not self.distorted or len(pts) == 0:
            xy = (pts - (self.cx, self.cy)) / (self.fx, self.fy)
        else:
            xy = self.solver_camera().unproject(pts)
        return np.c_[xy, np.ones(len(xy))]

    def undistort(self, px: np.ndarray) -> np.ndarray:
        """Distorted pixels [N, 2] -> pixels [N, 2] float64 of the ideal pinhole camera `k`."""
        return project(self.k, self.rays(px))

    def project(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points [N, 3] (z > 0) -> distorted pixels [N, 2] of this camera."""
        xy = points[:, :2] / points[:, 2:3]
        if not self.distorted:
            return xy * (self.fx, self.fy) + (self.cx, self.cy)
        return self.solver_camera().project(np.ascontiguousarray(xy, np.float64))

    def pack(self) -> bytes:
        """Fixed-size little-endian record (stored with each keyframe's features)."""
        d = list(self.d) + [0.0] * (8 - len(self.d))
        return _PACK.pack(
            b"CAM1", 1, _MODEL_CODES[self.distortion_model],
            self.width, self.height, self.fx, self.fy, self.cx, self.cy, 0.0, 0.0, *d,
        )  # fmt: skip

    @classmethod
    def unpack(cls, data: bytes) -> CameraModel:
        magic, _, code, width, height, fx, fy, cx, cy, _, _, *d = _PACK.unpack(data)
        if magic != b"CAM1" or code >= len(_MODEL_CODES):
            raise GeometryInputError("stored camera record is not a camera model (damaged?)")
        model = list(DISTORTION_MODELS)[code]
        n = max(DISTORTION_MODELS[model])
        return cls(width, height, fx, fy, cx, cy, model, tuple(d[:n]) if n else ())


def project(k: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Camera-frame points [N, 3] -> pixels [N, 2] of the pinhole camera `k` [3, 3]."""
    z = points[:, 2:3]
    return (points[:, :2] / z) * (k[0, 0], k[1, 1]) + (k[0, 2], k[1, 2])


def solver_model(c: CameraModel) -> tuple[str, list[float]]:
    """(PoseLib model name, its parameters) of a camera: ROS's plumb_bob is OpenCV's model
    (OPENCV: k1 k2 p1 p2; FULL_OPENCV when k3 is set), rational_polynomial FULL_OPENCV (k1 k2
    p1 p2 k3 k4 k5 k6), equidistant OPENCV_FISHEYE (k1 k2 k3 k4): camera_info's D as it is."""
    k = [c.fx, c.fy, c.cx, c.cy]
    if not c.distorted:
        return "PINHOLE", k
    d = list(c.d) + [0.0] * (8 - len(c.d))
    if c.distortion_model == "equidistant":
        return "OPENCV_FISHEYE", k + d[:4]
    if c.distortion_model == "plumb_bob" and d[4] == 0.0:
        return "OPENCV", k + d[:4]
    return "FULL_OPENCV", k + d[:8]


@lru_cache(maxsize=64)
def _solver_camera(c: CameraModel) -> poselib.Camera:
    name, params = solver_model(c)
    return poselib.Camera(name, params, c.width, c.height)


def camera_from_info(msg: Any) -> CameraModel:
    """A ``sensor_msgs/CameraInfo`` (rclpy, rosbags or any object with ``k``, ``d``,
    ``distortion_model``, ``width``, ``height``) -> CameraModel; GeometryInputError if unusable."""
    try:
        k = np.asarray(msg.k, np.float64).ravel()
        d = tuple(float(v) for v in np.asarray(msg.d, np.float64).ravel())
        model = str(msg.distortion_model or "none") if d else "none"
        width, height = int(msg.width), int(msg.height)
    except (AttributeError, TypeError, ValueError) as err:
        raise GeometryInputError(f"not a CameraInfo message: {err}") from err
    if k.shape != (9,):
        raise GeometryInputError(f"CameraInfo k must hold 9 values, got {k.size}")
    return CameraModel(width, height, k[0], k[4], k[2], k[5], model, d)


def camera_from_params(
    width: int,
    height: int,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    distortion_model: str = "none",
    d: tuple[float, ...] | list[float] = (),
) -> CameraModel:
    """Intrinsics given as parameters (the node's fallback when no camera_info arrives)."""
    d = tuple(float(v) for v in d)
    return CameraModel(int(width), int(height), float(fx), float(fy), float(cx), float(cy),
                       distortion_model if d else "none", d)  # fmt: skip
