"""Pinhole camera with yaw-only poses, near-plane clipping and flat-shaded 3D primitives.

Camera frame: X right, Y down, Z forward; the camera sits `height_m` above the ground with zero
pitch and roll, so vertical world edges stay vertical; the horizon is the image row `cy`, set below
the middle (a shifted lens, not a tilt) so facades fill more of the frame than the road.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

SHIFT = 4  # fractional bits for cv2 drawing calls (sub-pixel polygon corners)


@dataclass(frozen=True)
class Camera:
    """Image size, horizontal field of view and mounting height of the demo camera."""

    width: int = 320
    height: int = 240
    hfov_deg: float = 90.0
    height_m: float = 1.6  # m above the ground
    near: float = 0.3  # m, near clipping plane
    far: float = 260.0  # m, nothing farther is drawn
    horizon: float = 0.6  # horizon row as a fraction of the image height

    # Derived intrinsics are cached: the renderer reads them thousands of times per frame.
    @cached_property
    def f(self) -> float:
        """Focal length in pixels (square pixels)."""
        return self.width / 2 / math.tan(math.radians(self.hfov_deg) / 2)

    @cached_property
    def cx(self) -> float:
        return self.width / 2 - 0.5

    @cached_property
    def cy(self) -> float:
        return self.height * self.horizon - 0.5

    @cached_property
    def tan_half(self) -> float:
        """Horizontal frustum slope with a 2 px margin."""
        return (self.width / 2 + 2) / self.f


def to_camera(pts: np.ndarray, pose: np.ndarray, cam: Camera) -> np.ndarray:
    """World points [..., 3] (or [..., 2] on the ground) -> camera coordinates [..., 3]."""
    x, y, yaw = float(pose[0]), float(pose[1]), float(pose[2])
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = pts[..., 0] - x, pts[..., 1] - y
    z = pts[..., 2] if pts.shape[-1] == 3 else np.zeros_like(dx)
    return np.stack([dx * s - dy * c, cam.height_m - z, dx * c + dy * s], axis=-1)


def project(pc: np.ndarray, cam: Camera) -> np.ndarray:
    """Camera points [..., 3] with Z > 0 -> pixel coordinates [..., 2]."""
    inv = 1.0 / pc[..., 2]
    return np.stack([cam.cx + cam.f * pc[..., 0] * inv, cam.cy + cam.f * pc[..., 1] * inv], -1)


def clip_near(pc: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-frame polygon [K, 3] against Z >= near -> [K', 3]."""
    out = []
    for k in range(len(pc)):
        a, b = pc[k], pc[(k + 1) % len(pc)]
        if a[2] >= near:
            out.append(a)
        if (a[2] >= near) != (b[2] >= near):
            out.append(a + (b - a) * ((near - a[2]) / (b[2] - a[2])))
    return np.array(out).reshape(-1, 3)


def fill_polygon(
    img: np.ndarray, pc: np.ndarray, colour: tuple[float, ...] | float, cam: Camera, y0: int = 0
) -> None:
    """Fill camera-frame polygon [K, 3] into `img` (rows start at image row `y0`)."""
    if pc[:, 2].min() < cam.near:
        pc = clip_near(pc, cam.near)
    if len(pc) < 3:
        return
    px = project(pc, cam) - (0.0, y0)
    px = np.clip(px, -1e5, 1e5)
    cv2.fillPoly(img, [np.round(px * (1 << SHIFT)).astype(np.int32)], colour, cv2.LINE_8, SHIFT)


def camera_to_base(cam: Camera) -> tuple[float, ...]:
    """Pose of the camera's optical frame (x right, y down, z forward) in ``base_link`` (x forward,
    y left, z up) as ``(x, y, z, qx, qy, qz, qw)``: ``cam.height_m`` straight above the base."""
    half = 0.5  # the rotation [[0, 0, 1], [-1, 0, 0], [0, -1, 0]] as a quaternion
    return (0.0, 0.0, float(cam.height_m), -half, half, -half, half)
