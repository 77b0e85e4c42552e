"""The report's ground truth, per row, known once the replay is over: whether each candidate is a
true match, whether the keyframe's loop is true or false, and whether it is a missed revisit
(a true match existed, no true loop was accepted). Written as ``index.js`` with the row flags
the page filters by."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pair_vpr_ros.offline.report.decision_log import DecisionLog
from pair_vpr_ros.offline.report.html.rows import ACCEPTED, POSE_REFUSED, VERIFY_REJECTED
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo, KeyframeLookup, is_true_loop

FALSE, MISSED, TRUE, REVISIT = 2, 4, 32, 64  # flags added here
FLAG_NAMES = {"accepted": ACCEPTED, "false": FALSE, "missed": MISSED,
              "verification": VERIFY_REJECTED, "pose": POSE_REFUSED, "true": TRUE,
              "revisit": REVISIT}  # fmt: skip


def row_labels(
    log: DecisionLog,
    flags: bytearray,
    identity: tuple[str, str],
    keyframes: Sequence[KeyframeInfo],
    revisits: np.ndarray | None,
    gt_radius: float,
    exclusion_s: float,
) -> tuple[list[int], list[str]]:
    """(flags of every row with FALSE / TRUE / MISSED / REVISIT added, each row's candidates
    as a string: 't' true match, 'f' not, '-' unknown). `revisits` [len(keyframes)] bool: which
    keyframes have a true match (`loop_truth.true_match_mask`; None: no ground truth)."""
    lookup = KeyframeLookup(keyframes)
    has_match: dict[tuple[bool, float], bool] = {}
    if revisits is not None:
        for k, hit in zip(keyframes, revisits, strict=True):
            has_match[(k.stored, k.id if k.stored else k.stamp)] = bool(hit)
    accepted: dict[int, list[int]] = {}
    for row, rank in log.accepted:
        accepted.setdefault(row, []).append(rank)
    out_flags, out_labels = [], []
    for row in range(len(log)):
        map_id, stamp = log.map_id[row], log.stamp[row]
        query = lookup.by_id.get(map_id) if map_id >= 0 else lookup.by_stamp.get(stamp)
        key = (True, map_id) if map_id >= 0 else (False, stamp)
        labels = []
        for cand in log.candidates(row):
            own = cand.prior < 0 and (cand.robot, cand.session) == identity
            label = is_true_loop(query, lookup.by_id.get(cand.id), gt_radius, exclusion_s) \
                if own else None  # fmt: skip
            labels.append({True: "t", False: "f", None: "-"}[label])
        flag = flags[row] if row < len(flags) else 0
        ranks = [c.rank_before for c in log.candidates(row)]
        for rank in accepted.get(row, ()):
            label = labels[ranks.index(rank)]
            flag |= TRUE if label == "t" else FALSE if label == "f" else 0
        if has_match.get(key, False):
            flag |= REVISIT | (0 if flag & TRUE else MISSED)
        out_flags.append(flag)
        out_labels.append("".join(labels))
    return out_flags, out_labels


def write_index(folder: Path, flags: list[int], labels: list[str], chunk: int) -> None:
    """index.js: ``PAIRVPR.index({...})`` with every row's flags and candidate labels."""
    data = {"rows": len(flags), "chunk": chunk, "flags": flags, "labels": labels,
            "names": FLAG_NAMES}  # fmt: skip
    text = json.dumps(data, separators=(",", ":"))
    (folder / "index.js").write_text(f"PAIRVPR.index({text});\n", encoding="utf-8")
