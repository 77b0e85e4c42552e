"""Depth-sensor noise: sigma_z = a + b z^2, robust depth at keypoints, 3-D point covariances.

Structured-light, time-of-flight and stereo depth all lose precision with the square of the
distance (stereo: sigma_z = z^2 sigma_disparity / (f B)). The defaults a = 1.2 mm,
b = 1.9 mm / m^2 follow the published Kinect noise study of Nguyen, Izadi and Lovell (3DIMPVT
2012: 0.0012 + 0.0019 (z - 0.4)^2 m; the (z - 0.4) offset is dropped, which is conservative);
Khoshelham and Oude Elberink (Sensors 2012) measured the same growth (about 1.4 mm z^2). For a
stereo camera set b = sigma_disparity / (f B), a = 0 (``stereo.stereo_noise_b``); stereo depth
from `stereo.sgbm_depth` also comes with its own sigma per pixel (the block's texture and the
left-right check), kept per keypoint (`Features.depth_sigma`) and used in its place.

A keypoint sits on a corner or an edge more often than not, and at a depth edge the nearest
pixel's depth is as likely the background's as the object's: the depth of a keypoint is the
median of a small window, and none where the window spans a depth discontinuity.
"""

from __future__ import annotations

import numpy as np

WINDOW = 2  # half-size of the window around a keypoint (5 x 5 pixels)


def depth_sigma(z: np.ndarray, a: float, b: float) -> np.ndarray:
    """Standard deviation (m) of depth readings z [N] (m): a + b z^2."""
    return a + b * np.square(z)


def _windows(image: np.ndarray, px: np.ndarray) -> np.ndarray:
    """[H, W] float image, pixels [M, 2] -> [M, 25] its 5 x 5 windows (NaN outside)."""
    h, w = image.shape
    u = np.clip(np.round(px[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.round(px[:, 1]).astype(np.int64), 0, h - 1)
    padded = np.pad(image.astype(np.float32), WINDOW, constant_values=np.nan)
    offsets = np.arange(-WINDOW, WINDOW + 1)
    rows = (v[:, None, None] + WINDOW + offsets[None, :, None]).repeat(len(offsets), 2)
    cols = (u[:, None, None] + WINDOW + offsets[None, None, :]).repeat(len(offsets), 1)
    return padded[rows, cols].reshape(len(px), -1)


def robust_depth_at(depth: np.ndarray, px: np.ndarray, a: float, b: float) -> np.ndarray:
    """Depth [H, W] metres (NaN: none) at keypoints [M, 2] -> [M] float32: the median of the
    5 x 5 window; NaN where fewer than half of it has depth or where it spans a depth edge
    (spread of its readings, the extreme one at each end left out, above 6 sigma_z + 5 % of
    the depth)."""
    win = _windows(depth, px)  # [M, 25]
    win[~(win > 0)] = np.nan  # 0, negative and NaN: no reading
    count = np.isfinite(win).sum(axis=1)
    out = np.full(len(px), np.nan, np.float32)
    enough = count * 2 >= win.shape[1]
    if not enough.any():
        return out
    sub = win[enough]
    z = np.nanmedian(sub, axis=1)
    ranked = np.sort(sub, axis=1)  # NaN last
    valid = count[enough]
    rows = np.arange(len(sub))
    spread = ranked[rows, valid - 2] - ranked[rows, 1]  # one stray reading each side ignored
    edge = spread > 6 * depth_sigma(z, a, b) + 0.05 * z
    out[np.flatnonzero(enough)[~edge]] = z[~edge]
    return out


def sigma_at(sigma: np.ndarray, px: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Per-pixel depth sigma [H, W] (m, NaN: none) at keypoints [M, 2] whose depth [M] came
    from `robust_depth_at` -> [M] float32: the median of its 5 x 5 window (as the depth is),
    NaN where the keypoint has no depth."""
    win = _windows(sigma, px)
    out = np.full(len(px), np.nan, np.float32)
    has = np.isfinite(depth) & np.isfinite(win).any(axis=1)
    if has.any():
        out[has] = np.nanmedian(win[has], axis=1)
    return out


def point_sigmas(
    z: np.ndarray, a: float, b: float, measured: np.ndarray | None = None
) -> np.ndarray:
    """Depth std [N] (m) of points at depth z [N]: the sensor's own per-point sigma where
    `measured` [N] holds one (stereo matching), else the model a + b z^2."""
    model = depth_sigma(z, a, b)
    if measured is None:
        return model
    return np.where(np.isfinite(measured) & (measured > 0), measured, model)


def point_covariances(
    rays: np.ndarray,
    z: np.ndarray,
    sigma_px: float,
    f: float,
    a: float,
    b: float,
    measured: np.ndarray | None = None,
) -> np.ndarray:
    """Covariances [N, 3, 3] (m^2) of the 3-D points rays [N, 3] (z = 1) * z [N] in their own
    camera: depth noise along the ray (`point_sigmas`), plus the keypoint's pixel noise across
    it."""
    s_z = point_sigmas(z, a, b, measured)
    lateral = (sigma_px * z / f) ** 2  # a pixel of error moves the point z / f sideways
    cov = s_z[:, None, None] ** 2 * np.einsum("ni,nj->nij", rays, rays)
    cov[:, 0, 0] += lateral
    cov[:, 1, 1] += lateral
    return cov
