"""What storing keyframe features compactly costs the relative poses (issue 34).

The 8 TUM fr1/rpy RGB-D frames of test/data/real (28 pairs with ground truth, `test/real_frames`):
each pair is posed as the pipeline poses a loop, the query's features as extracted (1000
keypoints with depth) against the match's features as the map gives them back: `full` (record
version 1, as extracted) or `compact` (version 2, geometry/feature_codec.py), and compact
records keeping other numbers of keypoints. Prints, per feature kind and storage, the stored
bytes per keyframe, pairs posed, and the median rotation / translation error and 6-dof
chi-square of the posed pairs.

    python benchmarks/bench_feature_storage.py
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))
from real_frames import chi2, median, tum_features, tum_truths  # noqa: E402

from pair_vpr_ros.geometry import relative_pose  # noqa: E402
from pair_vpr_ros.geometry.feature_codec import COMPACT_KEEP  # noqa: E402
from pair_vpr_ros.geometry.features import pack_features, unpack_features  # noqa: E402
from pair_vpr_ros.geometry.rotations import rotation_angle_deg  # noqa: E402


def rows(feats, stored, truths) -> list[dict]:
    out = []
    cv2.setRNGSeed(0)  # RANSAC draws from OpenCV's global generator: same draws every form
    for (i, j), truth in truths.items():
        res = relative_pose(feats[i], stored[j])
        row = {"status": res.status}
        if res.status and res.status != "scale-free":
            row["rot"] = rotation_angle_deg(truth[:3, :3] @ res.rotation.T)
            row["trans"] = float(np.linalg.norm(truth[:3, 3] - res.translation))
            row["chi2"] = chi2(truth, res.rotation, res.translation, res.covariance)[0]
        out.append(row)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--keep", default="400,500,700,1000", help="compact keypoint counts to try")
    args = p.parse_args(argv)
    truths = tum_truths()
    print("| features | stored as | bytes / keyframe | posed | rotation error | translation "
          "error | chi-square (6-dof) |\n|---|---|---|---|---|---|---|")  # fmt: skip
    for kind in ("sift", "orb"):
        feats = tum_features(kind)
        forms = [("full", False, None)] + [
            (f"compact, {k} kept" + (" (default)" if k == COMPACT_KEEP[kind] else ""), True, k)
            for k in (int(v) for v in args.keep.split(","))
        ]
        for label, compact, keep in forms:
            packed = [pack_features(f, compact, keep) for f in feats]
            posed = [r for r in rows(feats, [unpack_features(b) for b in packed], truths)
                     if r["status"]]  # fmt: skip
            size = np.mean([len(b) for b in packed]) / 1e3
            print(f"| {kind} | {label} | {size:.1f} KB | {len(posed)} / {len(truths)} | "
                  f"{median(posed, 'rot'):.3f} deg | {median(posed, 'trans') * 100:.2f} cm | "
                  f"{median(posed, 'chi2'):.1f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
