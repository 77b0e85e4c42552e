"""One keyframe's row of the report, as plain data for the page's script: its candidates (global
similarity, pair score or "not scored", rank before / after re-ranking), each decision with its
reason in words, inliers and pose. Written as the replay runs; the ground-truth labels come at
the end (`labels.py`)."""

from __future__ import annotations

import math
from typing import Any

from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import FrameOutcome
from pair_vpr_ros.loops.records import Candidate, LoopRecord, rerank_score
from pair_vpr_ros.messages.loop_image import pose_sigmas

# row flags, known when the keyframe is decided (labels.py adds the ground truth's)
ACCEPTED, VERIFY_REJECTED, POSE_REFUSED = 1, 8, 16


def _num(value: float, digits: int = 4) -> float | None:
    """JSON-safe: None for NaN / inf (shown as "not scored")."""
    return round(float(value), digits) if math.isfinite(value) else None


def ranks_after(candidates: list[Candidate], config: DetectorConfig) -> dict[int, int]:
    """rank_before -> rank after re-ranking among the scored candidates of its map (one list of
    all maps without `loop_per_map`), as `records.rank_by_pair_score` orders them."""
    groups: dict[int, list[Candidate]] = {}
    for c in candidates:
        if math.isfinite(c.pair_score):
            groups.setdefault(c.prior if config.loop_per_map else 0, []).append(c)
    out = {}
    for group in groups.values():
        group.sort(key=lambda c: (-c.rerank_score(config.global_weight), c.rank_before))
        out.update({c.rank_before: rank for rank, c in enumerate(group, 1)})
    return out


def reason_words(record: LoopRecord, config: DetectorConfig) -> str:
    """Why `record` was accepted or rejected, in a sentence with the numbers that decided."""
    c = config
    score = rerank_score(record.pair_score, record.global_similarity, c.global_weight)
    shown = f"{score:.2f}" if math.isfinite(score) else "none"
    verified = f"; {record.inliers} inliers >= {c.min_inliers}" if record.inliers >= 0 else ""
    if record.accepted:
        if math.isfinite(score) and score < c.score_threshold:
            return (f"accepted as the continuation of the previous loop: score {shown} >= "
                    f"{c.score_threshold:g} - sequence_margin {c.sequence_margin:g}"
                    f"{verified}")  # fmt: skip
        return f"accepted: score {shown} >= score_threshold {c.score_threshold:g}{verified}"
    reason = record.reason
    if reason == "below global floor":
        return (f"rejected, not re-ranked: best global similarity "
                f"{record.global_similarity:.3f} < global_floor {c.global_floor:g}")  # fmt: skip
    if reason == "score below threshold":
        return f"rejected: best score {shown} < score_threshold {c.score_threshold:g}"
    if reason.startswith("awaiting temporal consistency"):
        return (f"rejected: {reason.removeprefix('awaiting ')}: score {shown} passed, but "
                f"{c.temporal_consistency} keyframes in a row must agree")  # fmt: skip
    if reason.startswith("geometric verification failed"):
        return (f"rejected by geometric verification: {record.inliers} inliers < min_inliers "
                f"{c.min_inliers} (score {shown} passed)")  # fmt: skip
    if reason.startswith("geometric verification impossible"):
        return f"rejected by geometric verification: the match has no stored features ({shown})"
    return f"rejected: {reason} (score {shown})"


def no_decision_words(outcome: FrameOutcome, config: DetectorConfig) -> str:
    """Why a keyframe has no decision at all."""
    if "search" not in outcome.timings_ms:
        return (f"no candidate: every keyframe so far lies within the exclusion window "
                f"(exclude_recent_s {config.exclude_recent_s:g} s, the newest "
                f"{config.exclude_recent_keyframes}), or the map did not answer")  # fmt: skip
    return "no candidate returned by the map"


def record_data(record: LoopRecord, config: DetectorConfig, loop_image: str | None) -> dict:
    """One decision of the row: match (its rank before), accepted, reason in words, inliers,
    pose status and reason, pose sigmas (m, deg) and |t|, the loop image's file."""
    sigmas = pose_sigmas(record)
    t = math.sqrt(record.tx**2 + record.ty**2 + record.tz**2) if sigmas else math.nan
    return {
        "m": record.rank_before, "id": record.match_id, "a": int(record.accepted),
        "why": reason_words(record, config), "inl": record.inliers, "pose": record.pose_status,
        "pwhy": record.pose_reason, "sig": [_num(v) for v in sigmas] if sigmas else None,
        "t": _num(t, 3), "img": loop_image,
    }  # fmt: skip


def row_flags(records: list[LoopRecord], pose_on: bool) -> int:
    """ACCEPTED, VERIFY_REJECTED and POSE_REFUSED of a keyframe's decisions."""
    flags = 0
    for r in records:
        flags |= ACCEPTED if r.accepted else 0
        flags |= VERIFY_REJECTED if r.reason.startswith("geometric verification") else 0
        flags |= POSE_REFUSED if r.accepted and pose_on and not r.pose_status else 0
    return flags


def row_data(
    row: int,
    outcome: FrameOutcome,
    config: DetectorConfig,
    image_row: Any,
    loop_images: dict[int, str],
) -> dict:
    """The row of keyframe `row` (`outcome` not skipped). `image_row(candidate)`: the report row
    whose image shows it (-1: none, e.g. a prior map's); `loop_images`: rank_before of an
    accepted match -> its loop image's file."""
    after = ranks_after(outcome.candidates, config)
    candidates = [
        [
            c.id,
            image_row(c),
            _num(c.global_similarity),
            _num(c.pair_score),
            c.rank_before,
            after.get(c.rank_before),
            c.prior,
        ]  # fmt: skip
        for c in outcome.candidates
    ]
    decisions = [
        record_data(r, config, loop_images.get(r.rank_before)) for r in outcome.decisions()
    ]
    out = {
        "n": row, "k": outcome.keyframe_id if outcome.keyframe_id is not None else -1,
        "r": outcome.represented_by, "s": round(outcome.stamp, 3), "c": candidates,
        "d": decisions,
    }  # fmt: skip
    if not decisions:
        out["why"] = no_decision_words(outcome, config)
    return out
