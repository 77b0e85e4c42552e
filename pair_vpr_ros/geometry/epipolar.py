"""Two-view geometry without depth: fundamental-matrix verification and the essential matrix.

`verify_pair` is the detector's optional geometric verification (inliers of a fundamental-matrix
RANSAC on the same matches the pose uses; `verified_matches` also gives the inliers' points, which
the loop image draws). `essential_pose` gives the rotation and the
translation direction of T_match_query from ideal (undistorted) pixels; `centre_rim_chi2` checks
a monocular pose for a camera model that bends the rim (distortion left out), and
`row_split_variance` for a rolling shutter that bends it row by row.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from pair_vpr_ros.geometry import covariance as cv
from pair_vpr_ros.geometry.features import Features, match_features
from pair_vpr_ros.geometry.rotations import log_so3

CHI2_3DOF_95 = 7.815  # 95 % point of a chi-square with 3 degrees of freedom


def verify_pair(
    a: Features, b: Features, ratio: float = 0.8, ransac_px: float = 3.0
) -> tuple[int, float]:
    """-> (fundamental-matrix RANSAC inliers, inliers / matches); (0, 0.0) with fewer than 8
    matches."""
    inliers, share, _ = verified_matches(a, b, ratio, ransac_px)
    return inliers, share


def verified_matches(
    a: Features, b: Features, ratio: float = 0.8, ransac_px: float = 3.0
) -> tuple[int, float, np.ndarray]:
    """`verify_pair` with its inlier matches: (inliers, inliers / matches, points [I, 4]
    float32: x, y in a's image, x, y in b's image, pixels as the keypoints); no points with
    fewer than 8 matches or no fit."""
    none = np.zeros((0, 4), np.float32)
    if a.kind != b.kind:
        return 0, 0.0, none
    pairs = match_features(a, b, ratio)
    if len(pairs) < 8:
        return 0, 0.0, none
    pa, pb = a.keypoints[pairs[:, 0]], b.keypoints[pairs[:, 1]]
    if not (np.isfinite(pa).all() and np.isfinite(pb).all()):
        return 0, 0.0, none  # damaged keypoints verify nothing
    f, mask = cv2.findFundamentalMat(pa, pb, cv2.FM_RANSAC, ransac_px, 0.999)
    # no F fitted: OpenCV may hand back a mask of an earlier call, which counts nothing here
    if f is None or f.shape != (3, 3) or mask is None or len(mask) != len(pairs):
        return 0, 0.0, none
    keep = mask.ravel() != 0
    points = np.concatenate([pa[keep], pb[keep]], axis=1).astype(np.float32)
    return len(points), len(points) / len(pairs), points


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def essential_pose(
    px_q: np.ndarray, px_m: np.ndarray, k: np.ndarray, threshold_px: float, min_inliers: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """Ideal pixels [N, 2] of matched points in the query and match images (one camera matrix
    `k`) -> (R, unit t, inlier indices) of T_match_query (X_m = R X_q + t), or why not."""
    if len(px_q) < max(min_inliers, 5):
        return f"too few feature matches ({len(px_q)} < {max(min_inliers, 5)})"
    moved = float(np.median(np.linalg.norm(px_q - px_m, axis=1)))
    if moved < 0.5:
        return (f"degenerate motion: matched points moved {moved:.2f} px (the same view): no "
                "translation direction")  # fmt: skip
    e, mask = cv2.findEssentialMat(px_q, px_m, k, cv2.USAC_ACCURATE, 0.999, threshold_px)
    if e is None or e.shape != (3, 3) or mask is None:
        return "no essential matrix fits the matches"
    fitted = int(mask.sum())
    if fitted < min_inliers:
        return f"too few essential-matrix inliers ({fitted} < {min_inliers})"
    _, r, t, mask = cv2.recoverPose(e, px_q, px_m, k, mask=mask.copy())
    idx = np.flatnonzero(mask.ravel())
    if len(idx) < min_inliers:  # they fit E but lie in front of neither pair of cameras
        return (f"degenerate motion: {fitted} matches fit, {len(idx)} show parallax (a pure "
                "rotation or no motion): no translation direction")  # fmt: skip
    return r, t.ravel() / np.linalg.norm(t), idx


def sampson_residuals(px_q: np.ndarray, px_m: np.ndarray, k: np.ndarray):
    """Residual function of (R, t) for `covariance.jacobian`: signed Sampson distances [N] (px)
    of the matches under E = [t/|t|]x R (only the direction of t matters)."""
    kinv = np.linalg.inv(k)
    xq = np.c_[px_q, np.ones(len(px_q))]
    xm = np.c_[px_m, np.ones(len(px_m))]

    def residuals(r: np.ndarray, t: np.ndarray) -> np.ndarray:
        f = kinv.T @ skew(t / np.linalg.norm(t)) @ r @ kinv
        fq = xq @ f.T  # epipolar lines in the match image
        fm = xm @ f  # ... in the query image
        num = np.einsum("ni,ni->n", xm, fq)
        return num / np.sqrt(fq[:, 0] ** 2 + fq[:, 1] ** 2 + fm[:, 0] ** 2 + fm[:, 1] ** 2)

    return residuals


def parallax_deg(rays_q: np.ndarray, rays_m: np.ndarray, r: np.ndarray) -> float:
    """Median angle (deg) between matched rays once the rotation is removed: near 0 for a pure
    rotation, where the translation direction is undefined."""
    a = rays_q @ r.T
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = rays_m / np.linalg.norm(rays_m, axis=1, keepdims=True)
    cos = np.clip(np.einsum("ni,ni->n", a, b), -1.0, 1.0)
    return math.degrees(float(np.median(np.arccos(cos))))


def centre_rim_chi2(
    px_q: np.ndarray, px_m: np.ndarray, k: np.ndarray, pose: tuple, cov_rot: np.ndarray
) -> tuple[float, float]:
    """(chi-square, 3 dof; angle, deg) of the difference between the rotations that the inliers
    [N, 2] (ideal pixels) nearer the image centre and those farther out each reach when the
    essential-matrix pose (R, unit t) is refined on them alone (Gauss-Newton on the Sampson
    residuals: a local refinement, not a new RANSAC that may land on another solution);
    cov_rot [3, 3] is the full fit's rotation covariance (each half: about twice that). A
    radial distortion left out bends the rim's rays more than the centre's, and a near-
    degenerate motion lets the halves drift apart: the pose is less certain than it says."""
    radius = np.linalg.norm(px_q - k[:2, 2], axis=1) + np.linalg.norm(px_m - k[:2, 2], axis=1)
    centre = radius <= np.median(radius)
    if min(centre.sum(), (~centre).sum()) < 8:
        return 0.0, 0.0
    ends = [_refine(px_q[sel], px_m[sel], k, *pose)[0] for sel in (centre, ~centre)]
    d = log_so3(ends[0] @ ends[1].T)
    return float(d @ np.linalg.solve(4 * cov_rot, d)), math.degrees(float(np.linalg.norm(d)))


def row_split_variance(
    px_q: np.ndarray, px_m: np.ndarray, k: np.ndarray, pose: tuple, min_sigma_px: float
) -> tuple[float, float]:
    """(variance, rad^2 per axis; angle, deg) for a camera that bends its images row by row:
    the pose (R, unit t) is refined on the inliers [N, 2] (ideal pixels) in the upper rows and
    on those in the lower rows alone (as `centre_rim_chi2`); when the two rotations differ by
    more than their own Gauss-Newton covariances explain (chi-square, 3 dof, above its 95 %
    point), half their angle is added on each axis, else nothing. A rolling shutter reads the
    rows out at different times, so a camera that turns meanwhile bends each image by its own
    turn rate; the essential matrix absorbs that with a small residual and a wrong pose (TUM
    fr1/rpy, up to 83 deg/s: errors of 1-7 deg at a stated 0.2-0.3 deg; docs/real-cameras.md)."""
    rows = px_q[:, 1] + px_m[:, 1]
    low = rows <= np.median(rows)
    if min(low.sum(), (~low).sum()) < 8:
        return 0.0, 0.0
    (ra, ca), (rb, cb) = (_refine(px_q[s], px_m[s], k, *pose, min_sigma_px) for s in (low, ~low))
    d = log_so3(ra @ rb.T)
    angle = math.degrees(float(np.linalg.norm(d)))
    if ca is None or cb is None or float(d @ np.linalg.solve(ca + cb, d)) <= CHI2_3DOF_95:
        return 0.0, angle
    return float(d @ d) / 4.0, angle


def direction_basis(t: np.ndarray) -> np.ndarray:
    """[3, 2]: the two unit directions orthogonal to t (how its direction can change)."""
    return np.linalg.svd(t[None])[2][1:].T


def _refine(px_q, px_m, k, r, t, min_sigma_px: float | None = None, iterations: int = 5) -> tuple:
    """(R, its covariance [3, 3]) after Gauss-Newton on the Sampson residuals of these matches
    from (R, unit t); the covariance is None without `min_sigma_px` (not wanted) or when
    degenerate."""
    res = sampson_residuals(px_q, px_m, k)
    basis = np.zeros((6, 5))  # the two directions that turn t, then the rotation
    basis[:3, :2], basis[3:, 2:] = direction_basis(t), np.eye(3)
    for _ in range(iterations):
        jac = cv.jacobian(res, r, t) @ basis
        step = np.linalg.lstsq(jac, -res(r, t), rcond=None)[0]
        r, t = cv.perturbed(r, t, basis @ step)
        t = t / np.linalg.norm(t)
        basis[:3, :2] = direction_basis(t)
    if min_sigma_px is None:
        return r, None
    fit = cv.gauss_newton_covariance(cv.jacobian(res, r, t) @ basis, res(r, t), min_sigma_px)
    return r, None if fit is None else fit[0][2:, 2:]
