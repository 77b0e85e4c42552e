"""What a decision is about and what it records: a `Candidate` (a map keyframe considered for one
query, with its scores) and a `LoopRecord` (one loop-closure decision, accepted or with the reason
it was not: the CSV row and the topic layout), and the one order re-ranking sorts candidates by.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields

import numpy as np


@dataclass
class LoopRecord:
    """One loop-closure decision; field order is the CSV column order and the topic layout."""

    query_id: int  # -1: the query is not added (localization mode, or map_growth represented it)
    query_stamp: float
    query_frame_id: str
    match_id: int
    match_stamp: float
    match_frame_id: str
    # Who recorded each keyframe (identity.py); keyword-only so positional use stays as it was.
    query_robot: str = field(default="", kw_only=True)
    query_session: str = field(default="", kw_only=True)
    match_robot: str = field(default="", kw_only=True)
    match_session: str = field(default="", kw_only=True)
    pair_score: float  # NaN when re-ranking was skipped
    global_similarity: float
    rank_before: int  # 1-based rank of the match in the global (FAISS) list
    rank_after: int  # 1-based rank after re-ranking (among the scored candidates)
    candidates: int = 0  # candidates the map returned for this query (<= top_k)
    scored: int = 0  # of those, how many got a pair score (< candidates: the budget ran out)
    inliers: int = -1  # -1: not verified
    inlier_ratio: float = float("nan")
    accepted: bool = False
    reason: str = ""  # why it was not accepted; "" when accepted
    # Relative pose T_match_query (see geometry.relpose): the query camera's pose in the match
    # camera's optical frame. Only accepted loops get one; NaN / () when there is none.
    # "metric" (depth), "metric-odometry" (monocular, scale from an odometry baseline next to
    # the match keyframe), "scale-free" or "" (no pose: see pose_reason)
    pose_status: str = ""
    pose_reason: str = ""  # why there is no pose (no scale; where the scale came from)
    pose_inliers: int = -1  # PnP / essential-matrix inliers; -1 when not tried
    tx: float = float("nan")  # m (scale-free: a unit vector)
    ty: float = float("nan")
    tz: float = float("nan")
    qx: float = float("nan")
    qy: float = float("nan")
    qz: float = float("nan")
    qw: float = float("nan")
    covariance: tuple[float, ...] = ()  # 36 row-major, order (x, y, z, rx, ry, rz); () w/o pose
    # A rig of several cameras (loops/rig.py): which camera took each keyframe, its index in
    # the rig's `cameras` (0: the only camera, and every record of a single-camera node).
    query_camera: int = 0
    match_camera: int = 0
    # "": the pose is T_match_query between the two camera frames (the frame ids above); a
    # frame id (a rig's base frame): the pose of the query keyframe's base in the match
    # keyframe's base, T_base_a T_a_b T_b_base, with the covariance carried through
    pose_frame: str = ""

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Candidate:
    """A map keyframe considered for one query."""

    id: int
    stamp: float
    frame_id: str
    global_similarity: float
    rank_before: int
    pair_score: float = float("nan")
    robot: str = ""  # who recorded it (identity.py)
    session: str = ""
    prior: int = -1  # -1: the live map; i >= 0: the pipeline's i-th prior map (read-only)
    camera: int = 0  # the rig camera that took it (loops/rig.py; 0: the only camera)
    # The two directions' logits when the re-rank cascade scored them one at a time (NaN: not
    # scored that way, or scored both at once by full scoring); pair_score is their sum, NaN
    # until both are scored (`directions`)
    logit_qc: float = float("nan")  # logit(query first, candidate second)
    logit_cq: float = float("nan")  # logit(candidate first, query second)

    def rerank_score(self, global_weight: float = 0.0) -> float:
        """What re-ranking sorts by and the threshold compares (`DetectorConfig.global_weight`)."""
        return rerank_score(self.pair_score, self.global_similarity, global_weight)

    @property
    def directions(self) -> int:
        """2: scored both ways (`pair_score`); 1: one way only (the cascade left it there); 0:
        not scored."""
        if not math.isnan(self.pair_score):
            return 2
        return int(not math.isnan(self.logit_qc)) + int(not math.isnan(self.logit_cq))

    @property
    def group(self) -> tuple[int, str, str]:
        """(map, robot, session): ids are comparable only within one group."""
        return self.prior, self.robot, self.session


def rerank_score(pair_score: float, global_similarity: float, global_weight: float) -> float:
    """Pair score + global_weight x global similarity (the pair score alone at weight 0)."""
    if global_weight == 0:
        return pair_score
    return pair_score + global_weight * global_similarity


def best_record(records: list[LoopRecord], global_weight: float) -> LoopRecord | None:
    """The decision a keyframe reports among its maps' (one, or one a map): accepted first,
    then the best re-rank score, then the best global rank; None without records."""

    def order(r: LoopRecord) -> tuple:
        score = rerank_score(r.pair_score, r.global_similarity, global_weight)
        return not r.accepted, -score if math.isfinite(score) else math.inf, r.rank_before

    return min(records, key=order) if records else None


def rank_by_pair_score(
    candidates: list[Candidate], scores: np.ndarray, global_weight: float = 0.0
) -> list[Candidate]:
    """Store each candidate's pair score (``scores`` [K], in the order of ``candidates``) and
    return the candidates best re-rank score first (`rerank_score`); equal scores keep their
    global order. The node's decisions, the fleet owner's and ``pairvpr-eval``'s re-ranked
    recall all rank through this one function."""
    for cand, score in zip(candidates, scores, strict=True):
        cand.pair_score = float(score)
    return sorted(candidates, key=lambda c: (-c.rerank_score(global_weight), c.rank_before))
