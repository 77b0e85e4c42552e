"""Relative poses and covariances on real RGB-D frames with recorded poses, against OpenCV.

    python benchmarks/eval_real_relpose.py --suite
    python benchmarks/eval_real_relpose.py SET_DIR --fx 518 --fy 519 --cx 325.5 --cy 253.5 \
        --depth-scale 1000 [--features sift] [--distort K1] [--focal-error 0.05]

SET_DIR holds ``color/N.png``, ``depth/N.png|pgm`` (16-bit, ``--depth-scale`` units per metre)
and ``pose.txt`` (one line per frame N = 1, 2, ...: ``tx ty tz qx qy qz qw``, the camera's pose
in the world). No data is shipped: point it at frames whose licence you hold. Every ordered
pair (query i, match j < i) is posed with `relative_pose` and with plain OpenCV on the same
frames (SIFT or ORB, ratio test, ``solvePnPRansac`` from the match's depth; and
``findEssentialMat`` + ``recoverPose`` for the rotation). Prints per method: pairs posed, pairs
posed correctly (rotation < 1 deg, translation < 5 cm), median rotation / translation error,
and for ours the chi-square of the 6-dof error against the reported covariance (a calibrated
covariance: median 5.3) and of the 3-dof rotation error (median 2.4).

``--suite`` (no SET_DIR) reports on the real sets shipped in test/data/real/ (TUM RGB-D fr1/rpy
and OpenCV's stereo chessboard, ``test/real_frames.py``) instead: a Markdown table per set and
mode (RGB-D, monocular, lens distortion left out, stereo), OpenCV ORB / SIFT + solvePnPRansac
beside it.

``--distort K1`` warps the images with a radial distortion k1 (as a lens would) and tells the
pose code nothing about it (the "no camera_info" mistake); ``--focal-error`` scales the focal
lengths given to the pose code (a wrong calibration).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from pair_vpr_ros.geometry import PoseConfig, camera_from_params, extract_features, relative_pose
from pair_vpr_ros.geometry.rotations import quaternion_matrix, rotation_angle_deg


def load_set(root: Path, depth_scale: float) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """-> [(rgb [H, W, 3] uint8, depth [H, W] float32 m (NaN: none), T_world_camera [4, 4])]."""
    poses = [list(map(float, line.split())) for line in (root / "pose.txt").read_text().split("\n")
             if line.strip()]  # fmt: skip
    out = []
    for i, p in enumerate(poses, start=1):
        rgb = cv2.cvtColor(cv2.imread(str(root / "color" / f"{i}.png")), cv2.COLOR_BGR2RGB)
        dpath = next((root / "depth").glob(f"{i}.*"))
        raw = cv2.imread(str(dpath), cv2.IMREAD_UNCHANGED).astype(np.float32)
        depth = np.where(raw > 0, raw / depth_scale, np.nan).astype(np.float32)
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = quaternion_matrix(p[3:7]), p[:3]
        out.append((rgb, depth, t))
    return out


def distort_image(img: np.ndarray, k: np.ndarray, k1: float, nearest: bool = False) -> np.ndarray:
    """The image a lens with radial distortion k1 would have taken (same K)."""
    h, w = img.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    pts = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(pts, k, np.array([k1, 0, 0, 0], np.float64), P=k)
    mx, my = (ideal.reshape(h, w, 2)[..., i].astype(np.float32) for i in range(2))
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(img, mx, my, interp, borderValue=0)


def chi2(truth: np.ndarray, r: np.ndarray, t: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """(6-dof, rotation-only) chi-square of the error d = (t_true - t, log(R_true R^T))."""
    d = np.r_[truth[:3, 3] - t, cv2.Rodrigues(truth[:3, :3] @ r.T)[0].ravel()]
    rot = float(d[3:] @ np.linalg.solve(cov[3:, 3:], d[3:]))
    return float(d @ np.linalg.solve(cov, d)), rot


def opencv_pnp(fq, fm, k: np.ndarray, norm: int):
    """Plain OpenCV: ratio-test matches, 3D from the match's depth, solvePnPRansac defaults."""
    pairs = cv2.BFMatcher(norm).knnMatch(fq.descriptors if norm != cv2.NORM_L2 else
                                         fq.descriptors.astype(np.float32),
                                         fm.descriptors if norm != cv2.NORM_L2 else
                                         fm.descriptors.astype(np.float32), k=2)  # fmt: skip
    good = [(a.queryIdx, a.trainIdx) for a, b in (p for p in pairs if len(p) == 2)
            if a.distance < 0.8 * b.distance]  # fmt: skip
    if len(good) < 8:
        return None
    g = np.array(good)
    z = fm.depth[g[:, 1]]
    ok = np.isfinite(z)
    if ok.sum() < 6:
        return None
    px_m = fm.keypoints[g[ok, 1]].astype(np.float64)
    pts = np.c_[(px_m - k[:2, 2]) / (k[0, 0], k[1, 1]), np.ones(ok.sum())] * z[ok, None]
    found, rvec, tvec, inl = cv2.solvePnPRansac(pts, fq.keypoints[g[ok, 0]].astype(np.float64),
                                                k, None)  # fmt: skip
    if not found or inl is None:
        return None
    r_qm = cv2.Rodrigues(rvec)[0]
    r_e = _essential_rotation(fq.keypoints[g[:, 0]], fm.keypoints[g[:, 1]], k)
    return r_qm.T, -r_qm.T @ tvec.ravel(), r_e


def _essential_rotation(pq: np.ndarray, pm: np.ndarray, k: np.ndarray):
    e, mask = cv2.findEssentialMat(pq.astype(np.float64), pm.astype(np.float64), k, cv2.RANSAC)
    if e is None or e.shape != (3, 3):
        return None
    _, r, _, _ = cv2.recoverPose(e, pq.astype(np.float64), pm.astype(np.float64), k, mask=mask)
    return r


def evaluate(frames, k: np.ndarray, args) -> dict:
    h, w = frames[0][0].shape[:2]
    told = k.copy()
    told[0, 0] *= 1 + args.focal_error
    told[1, 1] *= 1 + args.focal_error
    cam = camera_from_params(w, h, told[0, 0], told[1, 1], told[0, 2], told[1, 2])
    feats = []
    for rgb, depth, _ in frames:
        if args.distort:
            rgb = distort_image(rgb, k, args.distort)
            depth = distort_image(depth, k, args.distort, nearest=True)
        feats.append(extract_features(rgb, args.features, args.max_features, 1 << 30, depth, cam))
    norm = cv2.NORM_HAMMING if args.features == "orb" else cv2.NORM_L2
    rows = []
    for i in range(len(frames)):
        for j in range(i):
            truth = np.linalg.inv(frames[j][2]) @ frames[i][2]  # T_match_query
            res = relative_pose(feats[i], feats[j], PoseConfig())
            row = {"pair": f"{i + 1}-{j + 1}", "status": res.status, "reason": res.reason,
                   "true_deg": rotation_angle_deg(truth[:3, :3]),
                   "true_m": float(np.linalg.norm(truth[:3, 3]))}  # fmt: skip
            if res.status:
                row["rot_deg"] = rotation_angle_deg(truth[:3, :3] @ res.rotation.T)
                if res.status != "scale-free":
                    row["trans_m"] = float(np.linalg.norm(truth[:3, 3] - res.translation))
                    row["chi2"], row["chi2_rot"] = chi2(truth, res.rotation, res.translation,
                                                        res.covariance)  # fmt: skip
                else:
                    row["chi2_rot"] = chi2(truth, res.rotation, truth[:3, 3], res.covariance)[1]
            cvr = opencv_pnp(feats[i], feats[j], told, norm)
            if cvr is not None:
                row["cv_rot_deg"] = rotation_angle_deg(truth[:3, :3] @ cvr[0].T)
                row["cv_trans_m"] = float(np.linalg.norm(truth[:3, 3] - cvr[1]))
                if cvr[2] is not None:
                    row["cv_e_rot_deg"] = rotation_angle_deg(truth[:3, :3] @ cvr[2].T)
            rows.append(row)
    return {"pairs": rows, "summary": summarise(rows)}


def _good(rot, trans) -> bool:
    return rot is not None and trans is not None and rot < 1.0 and trans < 0.05


def summarise(rows: list[dict]) -> dict:
    def med(key, subset=rows):
        v = [r[key] for r in subset if key in r]
        return (round(float(np.median(v)), 4), round(float(np.max(v)), 4)) if v else None

    cv_good = [r for r in rows if _good(r.get("cv_rot_deg"), r.get("cv_trans_m"))]
    ours_good = [r for r in rows if _good(r.get("rot_deg"), r.get("trans_m"))]
    both = [r for r in cv_good if _good(r.get("rot_deg"), r.get("trans_m"))]
    return {
        "pairs": len(rows),
        "ours_posed": sum(bool(r["status"]) for r in rows),
        "ours_good": len(ours_good),
        "opencv_posed": sum("cv_rot_deg" in r for r in rows),
        "opencv_good": len(cv_good),
        "opencv_good_also_ours": len(both),
        "ours_rot_deg_median_max": med("rot_deg"),
        "ours_trans_m_median_max": med("trans_m"),
        "opencv_pnp_rot_deg_median_max": med("cv_rot_deg"),
        "opencv_pnp_trans_m_median_max": med("cv_trans_m"),
        "opencv_essential_rot_deg_median_max": med("cv_e_rot_deg"),
        "chi2_median_max": med("chi2"),
        "chi2_rot_median_max": med("chi2_rot"),
    }


def _line(name: str, rows: list[dict], median, cv: list[dict] | None = None) -> str:
    posed = [r for r in rows if r.get("status", "cv")]
    big = [r for r in posed if r.get("rot_deg", 0) > 5 and r.get("chi2_rot", 0) > 100]
    cells = [name, f"{len(posed)} / {len(rows)}", f"{median(posed, 'rot_deg'):.2f}",
             f"{median(posed, 'trans_m'):.3f}", f"{median(posed, 'chi2'):.1f}",
             f"{median(posed, 'chi2_rot'):.2f}", str(len(big))]  # fmt: skip
    if cv is not None:
        cells.append(f"{len(cv)} / {len(rows)}, {median(cv, 'rot_deg'):.2f}")
    return "| " + " | ".join(c.replace("nan", "-") for c in cells) + " |"


def suite() -> int:
    """Print the tables of docs/real-cameras.md for the sets in test/data/real/."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
    import real_frames as rf  # the suite's loaders (one copy of them)

    truths = rf.tum_truths()
    cv = {k: rf.opencv_rows(k, truths) for k in ("orb", "sift")}
    head = ("| set, mode | posed | rotation error median (deg) | translation error median | "
            "chi^2 median (6 dof) | rotation chi^2 median | rot > 5 deg and chi^2 > 100 | "
            "OpenCV PnP, same detector kind: posed, rotation median |")  # fmt: skip
    print(head + "\n|" + " --- |" * 8)
    for kind in ("sift", "orb"):
        for depth in (True, False):
            for dist in (True, False):
                rows = rf.pose_rows(rf.tum_features(kind, depth, dist), truths)
                name = (f"TUM fr1/rpy {kind}, {'RGB-D' if depth else 'monocular'}, "
                        f"{'with distortion' if dist else 'distortion left out'}")  # fmt: skip
                print(_line(name, rows, rf.median, cv[kind] if depth and dist else None))
    feats, board_truths, config = rf.chessboard()
    rows = rf.pose_rows(feats, board_truths, config)
    print(_line("OpenCV stereo chessboard, SGBM depth (squares)", rows, rf.median))
    return 0


def main(argv: list[str] | None = None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if "--suite" in argv:
        return suite()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("set", type=Path, help="folder with color/, depth/, pose.txt")
    for name in ("fx", "fy", "cx", "cy"):
        p.add_argument(f"--{name}", type=float, required=True, help=f"intrinsics {name}, px")
    p.add_argument("--depth-scale", type=float, default=1000.0, help="depth units per metre")
    p.add_argument("--features", default="sift", choices=("sift", "orb"), help="feature kind")
    p.add_argument("--max-features", type=int, default=1000, help="keypoints per image")
    p.add_argument("--distort", type=float, default=0.0, help="radial k1 applied, not told")
    p.add_argument("--focal-error", type=float, default=0.0, help="relative focal error told")
    p.add_argument("--rows", action="store_true", help="print every pair too")
    args = p.parse_args(argv)
    try:
        frames = load_set(args.set, args.depth_scale)
    except (OSError, StopIteration, ValueError, cv2.error, AttributeError) as err:
        print(f"error: cannot read the set {args.set}: {err}", file=sys.stderr)
        return 1
    k = np.array([[args.fx, 0, args.cx], [0, args.fy, args.cy], [0, 0, 1.0]])
    out = evaluate(frames, k, args)
    if not args.rows:
        out.pop("pairs")
    print(json.dumps(out, indent=1, default=lambda v: round(v, 4) if isinstance(v, float)
                     else str(v)))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
