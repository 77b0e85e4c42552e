"""What the data show that no residual does: a camera model that is wrong for its images.

A pose fitted through such a model fits its own pixels well and is off all the same. Two signs:

* Halves of the inliers reach different poses (`split_variances`): PoseLib refines the pose on
  one half and on the other alone, split three ways (`split_keys`): upper / lower rows (a
  rolling shutter read out while the camera turns: TUM fr1/rpy turns up to 83 deg/s), centre /
  rim (a lens model that bends the rim), left / right columns (a turn during the readout, depth
  and colour taken apart). When the halves' rotations differ by more than their covariances
  explain (chi-square, 3 dof, 95 % point), half their angle goes on each rotation axis
  (`half_angle`): both halves are bent, so their difference is about the pose's error.
* A lens distortion nobody declared (`radial_check`): a radial distortion bends points more
  the farther they lie from the centre, so one radial coefficient k1 on both cameras, fitted to
  the same inliers with the pose (golden-section search; PoseLib refines the pose at each k1),
  explains them far better. n ln(RSS_0 / RSS_k1) is a likelihood ratio (chi-square, 1 dof, for
  a lens without distortion); above `LIKELIHOOD_RATIO`, with RSS_k1 at most `EXPLAINED` of
  RSS_0, the covariance is widened until it admits the error: x RSS_0 / RSS_k1 and by the
  pose's change between the two models on every axis (the k1 model is an estimate too).

A sharp global-shutter camera with a good calibration leaves both quiet (or nearly: a 95 % test
fires on one split in twenty); measured on real frames in docs/real-cameras.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.geometry.rotations import log_so3

# A chessboard held 12-24 squares from a stereo rig (SGBM depth) has a relief of 1-3 % of its
# size; a desk scene (TUM fr1) 10-40 %.
PLANAR_RELIEF = 0.05
CHI2_3DOF_95 = 7.815  # 95 % point of a chi-square with 3 degrees of freedom
MIN_HALF = 8  # inliers each half of a split needs
# A half whose rotation std is this many times the whole fit's does not fix the rotation alone
# (a near-degenerate half: one facade of the demo world refits 8 deg off at a std of 9.5 deg on
# one axis, where the whole fit is 0.5 deg off); its disagreement is not evidence. Half the
# inliers alone have about 1.4 times the std.
DEGENERATE_HALF = 6.0
WORDS = {"rows": "the upper and lower rows (rolling shutter?)",
         "rim": "the image centre and rim (lens model?)",
         "columns": "the left and right columns"}  # fmt: skip

# selection [N] bool -> (R of the pose refitted on it, its rotation covariance [3, 3] or None),
# or None when that half cannot tell (its points lie on a plane)
Refit = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray | None] | None]


def split_keys(px_a: np.ndarray, px_b: np.ndarray, centres: tuple) -> dict[str, np.ndarray]:
    """The inliers' pixels [N, 2] in both images and the images' centres -> one key [N] per
    split (its median divides the inliers)."""
    radius = sum(np.linalg.norm(p - c, axis=1) for p, c in zip((px_a, px_b), centres, strict=True))
    return {"rows": px_a[:, 1] + px_b[:, 1], "rim": radius, "columns": px_a[:, 0] + px_b[:, 0]}


def half_angle(ra: np.ndarray, rb: np.ndarray, cov: np.ndarray | None) -> tuple[float, float]:
    """((half the angle between rotations ra and rb)^2 per axis, rad^2, when their difference
    lies beyond its covariance `cov` [3, 3] at the 95 % point, else 0; the angle, deg)."""
    d = log_so3(ra @ rb.T)
    angle = math.degrees(float(np.linalg.norm(d)))
    if cov is None or float(d @ np.linalg.solve(cov, d)) <= CHI2_3DOF_95:
        return 0.0, angle
    return float(d @ d) / 4.0, angle


def split_variances(
    keys: dict[str, np.ndarray], refit: Refit, cov_rot: np.ndarray
) -> tuple[float, str]:
    """(rotation variance to add, rad^2 per axis: the sum over the splits that disagree; the
    words for the reason, "" when none does); `cov_rot` [3, 3]: the whole fit's rotation
    covariance (a half far less certain than it cannot tell, `DEGENERATE_HALF`)."""
    total, words = 0.0, []
    limit = DEGENERATE_HALF**2 * float(np.linalg.eigvalsh(cov_rot)[-1])
    for name, key in keys.items():
        low = key <= np.median(key)
        if min(low.sum(), (~low).sum()) < MIN_HALF:
            continue
        ends = refit(low), refit(~low)
        if any(e is None or e[1] is None or np.linalg.eigvalsh(e[1])[-1] > limit for e in ends):
            continue
        (ra, ca), (rb, cb) = ends
        var, angle = half_angle(ra, rb, ca + cb)
        if var > 0.0:
            total += var
            words.append(f"{WORDS[name]} disagree by {angle:.2f} deg")
    return total, "; ".join(words)


def is_planar(points: np.ndarray, relief: float = PLANAR_RELIEF) -> bool:
    """Whether 3-D points [N, 3] lie on one plane: their spread along the plane's normal is
    under `relief` of their spread along the plane's shorter axis. The essential matrix of a
    plane is ill-posed (a family of solutions fits it), so it cannot check such a pose."""
    if len(points) < 4:
        return True
    lam = np.linalg.eigvalsh(np.cov(points.T))  # ascending
    return bool(lam[0] <= relief**2 * lam[1])


K1_RANGE = 0.6  # |k1| searched (normalised radius ~0.8 at the corners of a 60-deg lens)
LIKELIHOOD_RATIO = 30.0  # chi-square (1 dof) of the k1 model's improvement: p < 1e-7
EXPLAINED = 0.8  # ... and k1 must remove at least 20 % of the residual sum of squares
SEARCH_STEPS = 18  # golden-section steps: k1 to ~1e-4 of the range


@dataclass
class LensFinding:
    """k1 that fits far better, the residual ratio RSS_0 / RSS_k1, the pose change (d_t [3],
    d_rot [3]) between the models and the inliers' residual RMS near the centre and at the rim
    (px)."""

    k1: float
    ratio: float
    change: np.ndarray
    centre_rim_px: tuple[float, float]

    def widen(self, cov: np.ndarray, scaled: bool) -> np.ndarray:
        """cov [6, 6] (or [5, 5] direction + rotation when not `scaled`) widened to admit it."""
        out = cov * self.ratio
        d_rot = float(np.linalg.norm(self.change[3:]))
        out[-3:, -3:] += np.eye(3) * d_rot**2
        if scaled:
            out[:3, :3] += np.eye(3) * float(np.linalg.norm(self.change[:3])) ** 2
        return out

    def reason(self) -> str:
        return (f"covariance x{self.ratio:.1f} + the change "
                f"{math.degrees(float(np.linalg.norm(self.change[3:]))):.2f} deg: a radial "
                f"distortion k1 = {self.k1:+.3f} fits the inliers {self.ratio:.1f}x better "
                f"(residual RMS {self.centre_rim_px[0]:.2f} px near the centre, "
                f"{self.centre_rim_px[1]:.2f} px at the rim): lens distortion left out of "
                "camera_info (D)?")  # fmt: skip


def with_k1(camera: CameraModel, k1: float) -> CameraModel:
    """The camera with one radial coefficient k1 (plumb_bob)."""
    return replace(camera, distortion_model="plumb_bob", d=(k1, 0.0, 0.0, 0.0))


# k1 -> (R, t, residuals [n]) of T_match_query refitted with that k1 on both cameras
LensRefit = Callable[[CameraModel | None], tuple[np.ndarray, np.ndarray, np.ndarray]]


def radial_check(
    cameras: tuple[CameraModel, CameraModel], refit: LensRefit, radius: np.ndarray
) -> LensFinding | None:
    """A finding when a radial k1 on both cameras (both without declared distortion) explains
    the inliers far better (module docstring); `refit(k1)` refits the pose with that k1 (0:
    the cameras as they are), `radius` [N] each inlier's distance from the centre (px), its
    residuals the first N (or N x 2) of refit's."""
    if any(c.distorted for c in cameras):
        return None  # declared: a wrong D is not this check's business
    r0, t0, res0 = refit(0.0)
    rss0 = float(np.sum(res0**2))
    if rss0 <= 0.0 or len(res0) < 20:
        return None

    def cost(k1: float) -> float:  # a k1 whose model folds over inside the image: no fit
        value = float(np.sum(refit(k1)[2] ** 2))
        return value if math.isfinite(value) else math.inf

    k1 = _golden(cost, -K1_RANGE, K1_RANGE)
    r1, t1, res1 = refit(k1)
    rss1 = float(np.sum(res1**2))
    if not 0.0 < rss1 < math.inf or len(res0) * math.log(rss0 / rss1) < LIKELIHOOD_RATIO:
        return None
    if rss1 > EXPLAINED * rss0:
        return None
    change = np.r_[t1 - t0, log_so3(r1 @ r0.T)]
    return LensFinding(k1, rss0 / rss1, change, _centre_rim(res0, radius))


def _centre_rim(res: np.ndarray, radius: np.ndarray) -> tuple[float, float]:
    per = np.linalg.norm(res.reshape(len(radius), -1), axis=1)
    inner = radius <= np.median(radius)
    return (float(np.sqrt(np.mean(per[inner] ** 2))),
            float(np.sqrt(np.mean(per[~inner] ** 2))))  # fmt: skip


def _golden(f: Callable[[float], float], lo: float, hi: float) -> float:
    g = (math.sqrt(5) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    fa, fb = f(a), f(b)
    for _ in range(SEARCH_STEPS):
        if fa < fb:
            hi, b, fb = b, a, fa
            a = hi - g * (hi - lo)
            fa = f(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = f(b)
    return a if fa < fb else b
