"""Depth for keyframes from a rectified stereo pair (OpenCV StereoSGBM).

Robots often have a stereo camera and no depth topic. With the left image (the one the pipeline
sees), the right image and the right camera's ``CameraInfo`` (its projection matrix P holds the
baseline: P[0, 3] = -fx B), a keyframe's depth is z = fx B / disparity. The pair must be
rectified (``image_rect`` topics: same size, rows aligned); an unrectified or mismatched pair is
refused with a `StereoInputError` saying why (the pipeline counts it and goes on without depth).
Stereo depth noise: sigma_z = z^2 sigma_d / (fx B) = z sigma_d / d, with the disparity's
sigma_d per pixel from what the matching had to go on (OpenCV's SGBM gives no cost): the
block's horizontal texture (`disparity_sigma`: weak gradients fix a disparity poorly) and how
far the right image's own match lands from it (`left_right_difference`; more than
MAX_LEFT_RIGHT_PX: no depth). Without it (`stereo_noise_b`): the depth-noise model with a = 0
and b = sigma_d / (fx B).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from pair_vpr_ros.errors import GeometryInputError

MAX_ROW_GAP_PX = 1.5  # median vertical offset of left-right matches allowed (rectified: ~0)
MIN_CHECK_MATCHES = 20  # left-right matches needed to judge the rectification
BLOCK = 5  # SGBM's matching block (px)
# Disparity noise per pixel (`disparity_sigma`): sigma_d^2 = s0^2 + 2 s_n^2 / sum(I_x^2) over
# the block, the spread of a block-matching minimum under image noise s_n (grey levels, both
# images), plus s0 (sub-pixel interpolation, pixel locking), at most MAX_DISPARITY_SIGMA.
# Measured (docs/real-cameras.md): s0 = the disparity error RMS at the real chessboard's
# corners, 0.35 px (0.32 robust on textured demo-world blocks); s_n: weakly textured demo-world
# blocks err 1.2-1.8 px where s_n = 2 said 0.6, s_n = 3 says 0.9.
IMAGE_NOISE_GREY = 3.0
SUBPIXEL_SIGMA_PX = 0.35
# Left-right consistency: the right image's own matching (run on the flipped pair) must land
# within this of the left's, and the difference joins sigma_d. On the chessboard it finds 11 of
# the 14 corners whose SGBM depth is off by 15-150 squares (SGBM's own disp12MaxDiff let them
# through); at the others it is 0.06 px (median).
MAX_LEFT_RIGHT_PX = 2.0
MAX_DISPARITY_SIGMA_PX = 4.0


class StereoInputError(GeometryInputError):
    """A stereo pair that cannot give depth (what is wrong, what to do)."""


def stereo_baseline(info: Any) -> float:
    """Baseline B (m) from the right camera's ``CameraInfo`` (rclpy, rosbags or duck-typed):
    B = -P[0, 3] / P[0, 0]; StereoInputError when P has none."""
    try:
        p = np.asarray(info.p, np.float64).ravel()
    except (AttributeError, TypeError, ValueError) as err:
        raise StereoInputError(f"right camera_info: not a CameraInfo message ({err})") from err
    if p.shape != (12,) or not np.all(np.isfinite(p)) or p[0] <= 0:
        raise StereoInputError("right camera_info: P must hold 12 finite values with fx > 0")
    baseline = -p[3] / p[0]
    if not baseline > 0:
        raise StereoInputError(
            f"right camera_info: P[0, 3] = {p[3]:g} gives no positive baseline; it must be the "
            "RIGHT camera of a rectified pair (P[0, 3] = -fx * baseline)"
        )
    return float(baseline)


def stereo_noise_b(fx: float, baseline: float, sigma_disparity: float = 0.5) -> float:
    """The depth-noise model's b (1/m) of a stereo pair: sigma_d / (fx B)."""
    return sigma_disparity / (fx * baseline)


def _grey(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def check_pair(left: np.ndarray, right: np.ndarray) -> None:
    """StereoInputError unless `left` and `right` [H, W(, 3)] uint8 look like a rectified pair:
    same size, matched ORB features on the same rows (median |dy| <= 1.5 px), right of the
    left image's (positive disparity)."""
    if left.shape[:2] != right.shape[:2]:
        raise StereoInputError(
            f"stereo pair sizes differ: left {left.shape[1]}x{left.shape[0]}, right "
            f"{right.shape[1]}x{right.shape[0]}: subscribe both rectified images of one camera"
        )
    orb = cv2.ORB_create(800)
    kl, dl = orb.detectAndCompute(_grey(left), None)
    kr, dr = orb.detectAndCompute(_grey(right), None)
    if dl is None or dr is None:
        return  # featureless: nothing to judge, SGBM will find little anyway
    matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    if len(matches) < MIN_CHECK_MATCHES:
        return
    pl = np.array([kl[m.queryIdx].pt for m in matches])
    pr = np.array([kr[m.trainIdx].pt for m in matches])
    dy, dx = np.median(np.abs(pl[:, 1] - pr[:, 1])), np.median(pl[:, 0] - pr[:, 0])
    if dy > MAX_ROW_GAP_PX:
        raise StereoInputError(
            f"stereo pair is not rectified: matched features are {dy:.1f} px apart vertically "
            f"(at most {MAX_ROW_GAP_PX} px): use the image_rect topics (stereo_image_proc)"
        )
    if dx < 0:
        raise StereoInputError(
            f"stereo pair looks swapped: features sit {-dx:.1f} px further right in the left "
            "image than in the right one: swap image_topic and right_image_topic"
        )


def stereo_depth(
    left: np.ndarray, right: np.ndarray, fx: float, baseline: float, max_disparity: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Rectified left / right images [H, W(, 3)] uint8, focal length fx (px) and baseline B (m)
    -> (depth [H, W] float32 metres of the left image (NaN: none) from semi-global matching,
    its std [H, W] float32 m from `disparity_sigma`). `max_disparity` 0: an eighth of the
    width (objects at least 8 B fx / W away)."""
    check_pair(left, right)
    return sgbm_depth(left, right, fx, baseline, max_disparity)


def disparity_sigma(grey: np.ndarray) -> np.ndarray:
    """Left image [H, W] uint8 -> disparity std [H, W] float32 (px) of a block match at each
    pixel: sqrt(s0^2 + 2 s_n^2 / E), E = sum of the squared horizontal gradient (grey levels
    per px, central differences) over the BLOCK x BLOCK window. A flat or row-wise striped
    block gets MAX_DISPARITY_SIGMA_PX, a corner or a vertical edge about s0."""
    gx = cv2.Sobel(grey.astype(np.float32), cv2.CV_32F, 1, 0, ksize=1, scale=0.5)
    energy = cv2.boxFilter(gx * gx, -1, (BLOCK, BLOCK), normalize=False,
                           borderType=cv2.BORDER_REFLECT)  # fmt: skip
    var = SUBPIXEL_SIGMA_PX**2 + 2 * IMAGE_NOISE_GREY**2 / np.maximum(energy, 1e-6)
    return np.minimum(np.sqrt(var), MAX_DISPARITY_SIGMA_PX).astype(np.float32)


def sgbm_depth(
    left: np.ndarray, right: np.ndarray, fx: float, baseline: float, max_disparity: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """`stereo_depth` without `check_pair`, for a pair known to be rectified (ORB matches on
    strongly repeated texture, e.g. OpenCV's stereo chessboard sample, can fool the check)."""
    gl, gr = _grey(left), _grey(right)
    n = max_disparity or max(16, gl.shape[1] // 8)
    n = int(math.ceil(n / 16) * 16)
    block = BLOCK
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=n, blockSize=block,
        P1=8 * block * block, P2=32 * block * block, disp12MaxDiff=1,
        uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )  # fmt: skip
    disparity = sgbm.compute(gl, gr).astype(np.float32) / 16.0
    flipped = sgbm.compute(np.ascontiguousarray(gr[:, ::-1]), np.ascontiguousarray(gl[:, ::-1]))
    lr = left_right_difference(disparity, flipped[:, ::-1].astype(np.float32) / 16.0)
    depth = np.full(disparity.shape, np.nan, np.float32)
    sigma = np.full(disparity.shape, np.nan, np.float32)
    ok = (disparity > 0.5) & ~(lr > MAX_LEFT_RIGHT_PX)  # NaN (no right match): kept
    sigma_d = np.hypot(disparity_sigma(gl), np.nan_to_num(lr))
    depth[ok] = fx * baseline / disparity[ok]
    sigma[ok] = depth[ok] * sigma_d[ok] / disparity[ok]  # z^2 sigma_d / (fx B)
    return depth, sigma


def left_right_difference(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Disparities [H, W] (px, <= 0: none) of the left image and of the right one -> |d_L(x) -
    d_R(x - d_L(x))| [H, W] float32, NaN where either has none: how far the match found from
    the right image lands from the one found from the left."""
    h, w = left.shape
    cols = np.clip(np.arange(w)[None, :] - np.rint(left).astype(np.int64), 0, w - 1)
    back = right[np.arange(h)[:, None], cols]
    out = np.abs(left - back).astype(np.float32)
    out[(left <= 0) | (back <= 0)] = np.nan
    return out
