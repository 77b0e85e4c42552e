"""Relative poses and covariances on real frames: the project against PoseLib alone and OpenCV.

    python benchmarks/eval_real_relpose.py --suite
    python benchmarks/eval_real_relpose.py SET_DIR --fx 518 --fy 519 --cx 325.5 --cy 253.5 \
        --depth-scale 1000 [--features sift] [--distort K1] [--focal-error 0.05]

``--suite`` reports on the real sets shipped in test/data/real/ (TUM RGB-D fr1/rpy and OpenCV's
stereo chessboard, ``test/real_frames.py``): a Markdown table, one row per set and mode (RGB-D,
monocular, the lens distortion left out, the frames bent by a radial k1 nobody declares,
stereo), with the project's poses (`relative_pose`), PoseLib alone on the same matches
(`real_frames.poselib_rows`: its absolute pose from the match's depth, else its relative pose,
PoseLib's own options but the inlier thresholds) and OpenCV (its own ORB or SIFT, ratio 0.8,
``solvePnPRansac`` from the match's depth with the distortion) side by side: pairs posed and
median rotation error, and for the project the chi-square of the 6-dof error against the
reported covariance (a calibrated covariance: median 5.3) and of the 3-dof rotation error
(median 2.4).

SET_DIR holds ``color/N.png``, ``depth/N.png|pgm`` (16-bit, ``--depth-scale`` units per metre)
and ``pose.txt`` (one line per frame N = 1, 2, ...: ``tx ty tz qx qy qz qw``, the camera's pose
in the world). No data is shipped: point it at frames whose licence you hold. Every ordered
pair (query i, match j < i) is posed by the project, by PoseLib alone and by OpenCV
(``solvePnPRansac`` from the match's depth). ``--distort K1`` warps the images with a radial
distortion k1 (as a lens would) and tells the pose code nothing about it (the "no camera_info"
mistake); ``--focal-error`` scales the focal lengths given to the pose code.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
import real_frames as rf  # noqa: E402  (the suite's loaders and runners: one copy of them)

from pair_vpr_ros.geometry import camera_from_params, extract_features  # noqa: E402
from pair_vpr_ros.geometry.rotations import quaternion_matrix, rotation_angle_deg  # noqa: E402


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


def opencv_pnp(fq, fm, k: np.ndarray) -> np.ndarray | None:
    """Plain OpenCV on the features' keypoints: ratio-test matches, 3D from the match's depth,
    solvePnPRansac defaults -> R of T_match_query, or None."""
    norm = cv2.NORM_HAMMING if fq.kind == "orb" else cv2.NORM_L2
    pairs = cv2.BFMatcher(norm).knnMatch(fq.matchable(), fm.matchable(), k=2)
    good = [(a.queryIdx, a.trainIdx) for a, b in (p for p in pairs if len(p) == 2)
            if a.distance < 0.8 * b.distance]  # fmt: skip
    g = np.array(good).reshape(-1, 2)
    z = fm.depth[g[:, 1]]
    ok = np.isfinite(z)
    if ok.sum() < 6:
        return None
    pts = fm.camera.rays(fm.keypoints[g[ok, 1]]) * z[ok, None]
    found, rvec, _, inl = cv2.solvePnPRansac(pts, fq.keypoints[g[ok, 0]].astype(np.float64), k,
                                             None)  # fmt: skip
    return cv2.Rodrigues(rvec)[0].T if found and inl is not None and len(inl) >= 6 else None


def evaluate(frames, k: np.ndarray, args) -> dict:
    """Project, PoseLib alone and OpenCV on every pair of one set -> summary (and rows)."""
    h, w = frames[0][0].shape[:2]
    told = k.copy()
    told[0, 0] *= 1 + args.focal_error
    told[1, 1] *= 1 + args.focal_error
    cam = camera_from_params(w, h, told[0, 0], told[1, 1], told[0, 2], told[1, 2])
    feats = []
    for rgb, depth, _ in frames:
        if args.distort:
            rgb = rf.distort_image(rgb, k, args.distort)
            depth = rf.distort_image(depth, k, args.distort, nearest=True)
        feats.append(extract_features(rgb, args.features, args.max_features, 1 << 30, depth, cam))
    truths = {(i, j): np.linalg.inv(frames[j][2]) @ frames[i][2]
              for i in range(len(frames)) for j in range(i)}  # fmt: skip
    rows = rf.pose_rows(feats, truths)
    alone = rf.poselib_rows(feats, truths)
    opencv = []
    for (i, j), truth in truths.items():
        r = opencv_pnp(feats[i], feats[j], told)
        if r is not None:
            opencv.append({"pair": (i, j), "rot_deg": rotation_angle_deg(truth[:3, :3] @ r.T)})
    summary = {name: _summary(r) for name, r in (("project", rows), ("poselib", alone),
                                                  ("opencv", opencv))}  # fmt: skip
    return {"pairs": len(truths), "summary": summary, "rows": rows}


def _summary(rows: list[dict]) -> dict:
    posed = [r for r in rows if r.get("status", "posed")]
    out = {"posed": len(posed)}
    for key in ("rot_deg", "trans_m", "chi2", "chi2_rot"):
        v = [r[key] for r in posed if key in r]
        if v:
            out[f"{key}_median_max"] = (round(float(np.median(v)), 4), round(float(max(v)), 4))
    return out


def _line(name: str, rows, alone=None, opencv=None) -> str:
    posed = [r for r in rows if r["status"]]
    big = [r for r in posed if r.get("rot_deg", 0) > 5 and r.get("chi2_rot", 0) > 100]
    cells = [name, f"{len(posed)} / {len(rows)}", f"{rf.median(posed, 'rot_deg'):.2f}",
             f"{rf.median(posed, 'trans_m'):.3f}", f"{rf.median(posed, 'chi2'):.1f}",
             f"{rf.median(posed, 'chi2_rot'):.2f}", str(len(big))]  # fmt: skip
    for other in (alone, opencv):
        cells.append("" if other is None else
                     f"{len(other)} / {len(rows)}, {rf.median(other, 'rot_deg'):.2f}")  # fmt: skip
    return "| " + " | ".join(c.replace("nan", "-") for c in cells) + " |"


def suite() -> int:
    """Print the table of docs/real-cameras.md for the sets in test/data/real/."""
    truths = rf.tum_truths()
    cv = {k: rf.opencv_rows(k, truths) for k in ("orb", "sift")}
    print(
        "| set, mode | posed | rotation error median (deg) | translation error median | "
        "chi^2 median (6 dof) | rotation chi^2 median | rot > 5 deg and rot chi^2 > 100 | "
        "PoseLib alone: posed, rotation median | OpenCV PnP: posed, rotation median |"
    )
    print("|" + " --- |" * 9)
    for kind in ("sift", "orb"):
        for depth in (True, False):
            for dist in (True, False):
                name = (f"TUM fr1/rpy {kind}, {'RGB-D' if depth else 'monocular'}"
                        f"{'' if dist else ', distortion left out'}")  # fmt: skip
                feats = rf.tum_features(kind, depth, dist)
                print(_line(name, rf.tum_rows(kind, depth, dist), rf.poselib_rows(feats, truths),
                            cv[kind] if depth and dist else None), flush=True)  # fmt: skip
    for k1 in (-0.2, 0.2):
        feats = rf.tum_warped_features(k1)
        print(
            _line(
                f"TUM fr1/rpy sift, RGB-D, bent by k1 = {k1:+.1f} (not declared)",
                rf.pose_rows(feats, truths),
                rf.poselib_rows(feats, truths),
            ),
            flush=True,
        )
    feats, board_truths, config = rf.chessboard()
    print(_line("OpenCV stereo chessboard, SGBM depth (squares)",
                rf.pose_rows(feats, board_truths, config),
                rf.poselib_rows(feats, board_truths, config)))  # fmt: skip
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
        out.pop("rows")
    print(json.dumps(out, indent=1, default=lambda v: round(v, 4) if isinstance(v, float)
                     else str(v)))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
