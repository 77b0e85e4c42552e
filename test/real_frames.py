"""Real camera frames shipped with the suite (test/data/real/, licences in each README.md).

* ``tum_fr1_rpy_subset``: 8 Kinect v1 colour + depth frames of TUM RGB-D fr1/rpy with motion
  capture ground truth (CC BY 4.0, Sturm et al., IROS 2012). Its lens has k1 = 0.26: left out,
  it is a real miscalibration.
* ``opencv_stereo_chessboard``: 13 left/right views of a 9 x 6 chessboard (OpenCV samples,
  BSD-3 / Apache-2.0). The rig is calibrated and rectified here from the board, each view's
  pose is the board's PnP pose (chessboard-square units), the keyframes' depth is SGBM's and
  their keypoints are the board's corners (a chessboard's own texture repeats too much for
  descriptor matching: what is tested is depth, PnP and covariance, not matching).

Also used by ``benchmarks/eval_real_relpose.py``.
"""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np
import poselib

from pair_vpr_ros.geometry import PoseConfig, camera_from_params, extract_features, relative_pose
from pair_vpr_ros.geometry.depth_noise import robust_depth_at, sigma_at
from pair_vpr_ros.geometry.features import Features, match_features
from pair_vpr_ros.geometry.rotations import (
    exp_so3,
    log_so3,
    quaternion_matrix,
    rotation_angle_deg,
)
from pair_vpr_ros.geometry.stereo import sgbm_depth, stereo_noise_b

ROOT = Path(__file__).resolve().parent / "data" / "real"
TUM = ROOT / "tum_fr1_rpy_subset"
CHESS = ROOT / "opencv_stereo_chessboard"
TUM_K = (517.3, 516.5, 318.6, 255.3)  # fx fy cx cy, Freiburg 1 colour camera
TUM_D = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)  # plumb_bob k1 k2 t1 t2 k3
BOARD = (9, 6)
CHESS_VIEWS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 14)
# The colour stamps trail the motion capture: OpenCV's own PnP poses (``opencv_rows``, SIFT and
# ORB) are closest to the ground truth taken 7.5-10 ms before each stamp (mean rotation error
# 0.68-0.69 deg against 0.80 deg at the stamp; the camera turns up to 83 deg/s here, 0.8 deg in
# 10 ms). `test_tum_colour_stamps_trail_the_ground_truth` keeps that measured.
TUM_STAMP_DELAY_S = 0.010
CHESS_MAX_DISPARITY = 192  # the board is 11-24 squares away: disparities up to ~160 px


def _associations() -> list[list[str]]:
    """associations.txt's rows: rgb stamp, rgb file, depth stamp, depth file, ..."""
    return [line.split() for line in (TUM / "associations.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]  # fmt: skip


@functools.cache
def tum_frames() -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]:
    """-> ((rgb [480, 640, 3] uint8, depth [480, 640] float32 m (NaN: none), T_world_camera
    [4, 4] when the colour image was taken: `tum_poses`), ...) in associations.txt order."""
    out = []
    for f, pose in zip(_associations(), tum_poses(), strict=True):
        rgb = cv2.cvtColor(cv2.imread(str(TUM / f[1])), cv2.COLOR_BGR2RGB)
        raw = cv2.imread(str(TUM / f[3]), cv2.IMREAD_UNCHANGED).astype(np.float32)
        depth = np.where(raw > 0, raw / 5000.0, np.nan).astype(np.float32)
        out.append((rgb, depth, pose))
    return tuple(out)


def tum_poses(delay_s: float = TUM_STAMP_DELAY_S) -> list[np.ndarray]:
    """T_world_camera [4, 4] of the 8 frames from the ground truth `delay_s` before each colour
    stamp."""
    return [_ground_truth_at(float(f[0]) - delay_s) for f in _associations()]


@functools.cache
def _ground_truth() -> np.ndarray:
    """[N, 8] rows of groundtruth.txt: stamp tx ty tz qx qy qz qw (camera to world)."""
    return np.loadtxt(TUM / "groundtruth.txt", comments="#")


def _ground_truth_at(stamp: float) -> np.ndarray:
    """T_world_camera [4, 4] at `stamp`, interpolated between the two motion-capture poses
    around it (100 Hz; the camera turns up to ~50 deg/s in fr1/rpy, 0.25 deg in 5 ms)."""
    gt = _ground_truth()
    k = int(np.clip(np.searchsorted(gt[:, 0], stamp), 1, len(gt) - 1))
    (s0, *p0), (s1, *p1) = gt[k - 1], gt[k]
    w = float(np.clip((stamp - s0) / (s1 - s0), 0.0, 1.0))
    r0, r1 = quaternion_matrix(p0[3:]), quaternion_matrix(p1[3:])
    pose = np.eye(4)
    pose[:3, :3] = r0 @ exp_so3(w * log_so3(r0.T @ r1))
    pose[:3, 3] = (1 - w) * np.asarray(p0[:3]) + w * np.asarray(p1[:3])
    return pose


def tum_camera(distortion: bool = True):
    """The TUM colour camera, with its lens distortion or (the mistake) without."""
    d = TUM_D if distortion else ()
    return camera_from_params(640, 480, *TUM_K, "plumb_bob" if distortion else "none", d)


@functools.cache
def tum_features(kind: str = "sift", depth: bool = True, distortion: bool = True):
    """Keyframe features of the 8 TUM frames, with or without depth and distortion."""
    cam = tum_camera(distortion)
    return tuple(extract_features(rgb, kind, 1000, 1 << 30, d if depth else None, cam)
                 for rgb, d, _ in tum_frames())  # fmt: skip


def distort_image(img: np.ndarray, k: np.ndarray, k1: float, nearest: bool = False) -> np.ndarray:
    """The image a lens with radial distortion k1 (plumb_bob) would have taken (same K)."""
    h, w = img.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    pts = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(pts, k, np.array([k1, 0, 0, 0], np.float64), P=k)
    mx, my = (ideal.reshape(h, w, 2)[..., i].astype(np.float32) for i in range(2))
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(img, mx, my, interp, borderValue=0)


@functools.cache
def tum_warped_features(k1: float, kind: str = "sift") -> tuple[Features, ...]:
    """RGB-D features of the 8 TUM frames undistorted with their own lens model, then bent by
    a radial k1 that the camera model (no distortion) is not told: an undeclared lens."""
    k = tum_camera().k
    maps = cv2.initUndistortRectifyMap(k, np.array(TUM_D), None, k, (640, 480), cv2.CV_32FC1)
    out = []
    for rgb, depth, _ in tum_frames():
        rgb, depth = (
            cv2.remap(rgb, *maps, cv2.INTER_LINEAR),
            cv2.remap(depth, *maps, cv2.INTER_NEAREST),
        )
        out.append(
            extract_features(
                distort_image(rgb, k, k1),
                kind,
                1000,
                1 << 30,
                distort_image(depth, k, k1, True),
                tum_camera(False),
            )
        )
    return tuple(out)


def tum_truths(delay_s: float = TUM_STAMP_DELAY_S) -> dict[tuple[int, int], np.ndarray]:
    """(query i, match j < i) -> true T_match_query [4, 4] (ground truth: `tum_poses`)."""
    poses = tum_poses(delay_s)
    return {(i, j): np.linalg.inv(poses[j]) @ poses[i] for i in range(8) for j in range(i)}


def chi2(truth: np.ndarray, r: np.ndarray, t: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """(6-dof, rotation-only) chi-square of the error d = (t_true - t, log(R_true R^T))."""
    d = np.r_[truth[:3, 3] - t, cv2.Rodrigues(truth[:3, :3] @ r.T)[0].ravel()]
    rot = float(d[3:] @ np.linalg.solve(cov[3:, 3:], d[3:]))
    return float(d @ np.linalg.solve(cov, d)), rot


def pose_rows(feats, truths: dict, config: PoseConfig | None = None) -> list[dict]:
    """Pose every pair with `relative_pose` -> [{pair, status, reason, rot_deg, trans_m, chi2,
    chi2_rot}] (errors against the truth; a scale-free pose has rotation figures only)."""
    rows = []
    cv2.setRNGSeed(0)  # RANSAC draws from OpenCV's global generator: same poses in any order
    for (i, j), truth in truths.items():
        res = relative_pose(feats[i], feats[j], config)
        row = {"pair": (i, j), "status": res.status, "reason": res.reason}
        if res.status:
            row["rot_deg"] = rotation_angle_deg(truth[:3, :3] @ res.rotation.T)
            if res.status == "scale-free":
                row["chi2_rot"] = chi2(truth, res.rotation, truth[:3, 3], res.covariance)[1]
            else:
                row["trans_m"] = float(np.linalg.norm(truth[:3, 3] - res.translation))
                row["chi2"], row["chi2_rot"] = chi2(truth, res.rotation, res.translation,
                                                    res.covariance)  # fmt: skip
        rows.append(row)
    return rows


@functools.cache
def tum_rows(kind: str, depth: bool = True, distortion: bool = True) -> tuple[dict, ...]:
    """`pose_rows` of the TUM pairs with the default `PoseConfig` (computed once a run)."""
    return tuple(pose_rows(tum_features(kind, depth, distortion), tum_truths()))


def poselib_rows(feats, truths: dict, config: PoseConfig | None = None) -> list[dict]:
    """PoseLib alone on the same matches as `pose_rows` (mutual ratio-test matches): its
    absolute pose from the match keyframe's depth when one is there, else its relative pose,
    with PoseLib's own options but the inlier thresholds of `config`; posed with at least
    `config.min_inliers` inliers -> [{pair, rot_deg}] of the pairs it poses."""
    c = config or PoseConfig()
    rows = []
    for (i, j), truth in truths.items():
        q, m = feats[i], feats[j]
        pairs = match_features(q, m, c.ratio)
        kq, km = (f.keypoints[pairs[:, k]].astype(np.float64) for f, k in ((q, 0), (m, 1)))
        if m.depth is not None:
            z = m.depth[pairs[:, 1]]
            ok = np.isfinite(z)
            pts = m.camera.rays(km[ok]) * z[ok, None]
            pose, info = poselib.estimate_absolute_pose(
                kq[ok], pts, q.camera.solver_camera(), {"max_reproj_error": c.ransac_px}
            )
            r = pose.R.T  # X_q = R X_m + t
        else:
            pose, info = poselib.estimate_relative_pose(
                kq, km, q.camera.solver_camera(), m.camera.solver_camera(),
                {"max_epipolar_error": c.essential_px})  # fmt: skip
            r = pose.R
        if info["num_inliers"] >= c.min_inliers:
            rows.append({"pair": (i, j), "rot_deg": rotation_angle_deg(truth[:3, :3] @ r.T)})
    return rows


def opencv_rows(kind: str, truths: dict) -> list[dict]:
    """A standard pipeline on the TUM frames: OpenCV ORB (or SIFT), ratio 0.8, 3-D points from
    the match's depth, ``solvePnPRansac`` with the lens distortion -> [{pair, rot_deg}] of the
    pairs it poses."""
    det = cv2.ORB_create(1000) if kind == "orb" else cv2.SIFT_create(1000)
    norm = cv2.NORM_HAMMING if kind == "orb" else cv2.NORM_L2
    k, d = tum_camera().k, np.array(TUM_D)
    found = [det.detectAndCompute(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), None)
             for rgb, _, _ in tum_frames()]  # fmt: skip
    rows = []
    cv2.setRNGSeed(0)
    for (i, j), truth in truths.items():
        (kq, dq), (km, dm) = found[i], found[j]
        good = [(a.queryIdx, a.trainIdx) for a, b in
                (p for p in cv2.BFMatcher(norm).knnMatch(dq, dm, k=2) if len(p) == 2)
                if a.distance < 0.8 * b.distance]  # fmt: skip
        px_q = np.array([kq[a].pt for a, _ in good]).reshape(-1, 2)
        px_m = np.array([km[b].pt for _, b in good]).reshape(-1, 2)
        z = robust_depth_at(tum_frames()[j][1], px_m, 0.0012, 0.0019)
        ok = np.isfinite(z)
        if ok.sum() < 6:
            continue
        pts = tum_camera().rays(px_m[ok]) * z[ok, None]
        done, rvec, tvec, inl = cv2.solvePnPRansac(pts, px_q[ok], k, d)
        if done and inl is not None and len(inl) >= 6:
            r_qm = cv2.Rodrigues(rvec)[0]  # X_q = R X_m + t
            rows.append({"pair": (i, j), "rot_deg": rotation_angle_deg(truth[:3, :3] @ r_qm)})
    return rows


@functools.cache
def chessboard():
    """-> (features of the 13 left views [13], truths {(i, j): T_match_query}, PoseConfig with
    the rig's stereo depth noise): rectified rig, SGBM depth, corners as keypoints."""
    obj = np.zeros((BOARD[0] * BOARD[1], 3), np.float32)
    obj[:, :2] = np.mgrid[0 : BOARD[0], 0 : BOARD[1]].T.reshape(-1, 2)
    grey = {s: [cv2.imread(str(CHESS / f"{s}{v:02d}.jpg"), 0) for v in CHESS_VIEWS]
            for s in ("left", "right")}  # fmt: skip
    stop = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    corners = {s: [cv2.cornerSubPix(g, cv2.findChessboardCorners(g, BOARD)[1], (11, 11),
                                    (-1, -1), stop) for g in grey[s]] for s in grey}  # fmt: skip
    size, objs = (640, 480), [obj] * len(CHESS_VIEWS)
    kl, dl = cv2.calibrateCamera(objs, corners["left"], size, None, None)[1:3]
    kr, dr = cv2.calibrateCamera(objs, corners["right"], size, None, None)[1:3]
    _, kl, dl, kr, dr, r, t, _, _ = cv2.stereoCalibrate(objs, corners["left"], corners["right"],
                                                        kl, dl, kr, dr, size,
                                                        flags=cv2.CALIB_FIX_INTRINSIC)  # fmt: skip
    r1, r2, p1, p2 = cv2.stereoRectify(kl, dl, kr, dr, size, r, t, alpha=0)[:4]
    maps = [cv2.initUndistortRectifyMap(k, d, rr, p, size, cv2.CV_32FC1)
            for k, d, rr, p in ((kl, dl, r1, p1), (kr, dr, r2, p2))]  # fmt: skip
    fx, baseline = p1[0, 0], -p2[0, 3] / p2[0, 0]
    cam = camera_from_params(640, 480, fx, p1[1, 1], p1[0, 2], p1[1, 2])
    b = stereo_noise_b(fx, baseline)
    code = np.random.default_rng(0).integers(0, 256, (len(obj), 128)).astype(np.uint8)
    feats, poses = [], []
    for v in range(len(CHESS_VIEWS)):
        left, right = (cv2.remap(grey[s][v], *maps[n], cv2.INTER_LINEAR)
                       for n, s in enumerate(("left", "right")))  # fmt: skip
        depth, sigma = sgbm_depth(left, right, fx, baseline, CHESS_MAX_DISPARITY)
        px = cv2.undistortPoints(corners["left"][v], kl, dl, R=r1, P=p1).reshape(-1, 2)
        _, rvec, tvec = cv2.solvePnP(obj, px, p1[:, :3], None)
        pose = np.eye(4)  # board -> left camera
        pose[:3, :3], pose[:3, 3] = cv2.Rodrigues(rvec)[0], tvec.ravel()
        poses.append(pose)
        px = px.astype(np.float32)
        z = robust_depth_at(depth, px, 0.0, b)
        feats.append(Features(px, code, "sift", z, cam, depth_sigma=sigma_at(sigma, px, z)))
    n = len(poses)
    truths = {(i, j): poses[j] @ np.linalg.inv(poses[i]) for i in range(n) for j in range(i)}
    return tuple(feats), truths, PoseConfig(depth_sigma_a=0.0, depth_sigma_b=b)


def median(rows: list[dict], key: str) -> float:
    """Median of `key` over the rows that have it (NaN when none)."""
    v = [r[key] for r in rows if key in r]
    return float(np.median(v)) if v else float("nan")
