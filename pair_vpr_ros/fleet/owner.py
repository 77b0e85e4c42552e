"""Owner-side re-ranking: the robot that owns candidate keyframes scores them against another
robot's query with its own stored dense tokens, and decides the inter-robot loop.

Pair-VPR's pair classifier needs both images' dense tokens. The requester sends its query's
tokens once (one keyframe, ~0.8 MB at ViT-B/322 fp16) with the ids of the owner's candidates;
the owner scores all of them against tokens it already has. The reverse (the owner sending K
candidates' tokens) would cost K times more. The query's packed keyframe features (~140 KB of
SIFT at 1000 keypoints; empty without geometry) travel too, so the owner can verify the pair and
compute the relative pose T_match_query with the same geometry code as an intra-robot loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.errors import FleetMessageError
from pair_vpr_ros.fleet.messages import ScoreRequest, ScoreResponse
from pair_vpr_ros.geometry.features import Features
from pair_vpr_ros.loops.growth import shift_pose
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.records import Candidate, LoopRecord, rank_by_pair_score
from pair_vpr_ros.loops.scoring import map_pair_scores

MAX_PIXEL = 1e5  # keypoints further out than this (px) are no image's
IDENTITY = ("query_robot", "query_session", "match_robot", "match_session")


@dataclass
class InterRobotLoop:
    """A loop between the requester's query keyframe and the owner's match keyframe."""

    record: LoopRecord
    query_robot: str
    query_session: str
    match_robot: str
    match_session: str

    def to_dict(self) -> dict:
        """The record's keys (loops.json), both sides' robot and session among them."""
        return self.record.to_dict()


def check_request(pipe: LoopClosurePipeline, req: ScoreRequest, robot: str, session: str) -> None:
    """FleetMessageError (its reason is counted) when this robot cannot score `req`."""
    if req.owner_robot != robot:
        raise FleetMessageError("not for this robot", f"request for {req.owner_robot!r}")
    if req.owner_session != session:
        raise FleetMessageError("stale session", f"request for session {req.owner_session!r}")
    want = (pipe.model.num_patches, pipe.model.config.embed_dim)
    if tuple(req.dense.shape) != want:
        raise FleetMessageError("wrong size", f"dense {list(req.dense.shape)}, not {list(want)}")
    size = len(pipe.place_map)
    bad = [i for i in req.candidate_ids if not 0 <= i < size]
    if bad or len(set(req.candidate_ids)) != len(req.candidate_ids):
        raise FleetMessageError("unknown keyframe", f"ids {bad or req.candidate_ids} of {size}")


def check_own_keyframes(pipe: LoopClosurePipeline, req: ScoreRequest, robot: str) -> None:
    """fleet_peer_search "milvus": the requester found the candidates as rows of the shared
    collection, which name the keyframe's robot and session. Each must be a keyframe of this
    robot's map of that session (one of an earlier run is fine: the map was loaded); anything
    else ("stale keyframe": a row of a run never saved, of another copy of the map) is refused
    before any scoring."""
    pm = pipe.place_map
    for kf_id in req.candidate_ids:
        ok = 0 <= kf_id < len(pm) and pm.identity(pm.meta(kf_id)) == (robot, req.owner_session)
        if not ok:
            raise FleetMessageError(
                "stale keyframe", f"id {kf_id} is no keyframe of {robot}/{req.owner_session} here"
            )


def score_request(
    pipe: LoopClosurePipeline, req: ScoreRequest, robot: str, session: str
) -> tuple[InterRobotLoop, ScoreResponse]:
    """Pair-score the owner's candidates of `req` (checked first) -> the loop decision (accepted
    when the best re-rank score reaches the detector's score_threshold and, with geometric
    verification on, the pair verifies) and the response for the requester."""
    check_request(pipe, req, robot, session)
    query = _request_features(pipe, req.features)  # checked before the scoring work
    pm = pipe.place_map
    cands = []
    pairs = zip(req.candidate_ids, req.similarities, strict=True)
    for rank, (kf_id, sim) in enumerate(pairs, start=1):
        meta = pm.meta(kf_id)
        cands.append(Candidate(kf_id, meta.stamp, meta.frame_id, float(sim), rank,
                               robot=meta.robot, session=meta.session))  # fmt: skip
    scores = map_pair_scores(pipe.model, pm, req.dense, req.candidate_ids, pipe.rerank_chunk)
    c = pipe.config
    best = rank_by_pair_score(cands, scores, c.global_weight)[0]
    record = LoopRecord(
        query_id=req.query_id, query_stamp=req.query_stamp, query_frame_id="",
        match_id=best.id, match_stamp=best.stamp, match_frame_id=best.frame_id,
        pair_score=best.pair_score, global_similarity=best.global_similarity,
        rank_before=best.rank_before, rank_after=1, candidates=len(cands), scored=len(cands),
    )  # fmt: skip
    below = best.rerank_score(c.global_weight) < c.score_threshold
    record.reason = "score below threshold" if below else ""
    # a keyframe stored without features (map_growth) is verified and posed with its feature
    # source's, and the pose composed into its frame, as the pipeline does for its own loops
    features, lent = pipe.match_features(best)
    if not record.reason and c.geometric_verification:
        record.inliers, record.inlier_ratio = pipe.geometry.verify(query, features)
        if record.inliers < c.min_inliers:
            record.reason = f"geometric verification failed ({record.inliers} inliers)"
    record.accepted = not record.reason
    if record.accepted and pipe.geometry.config.relative_pose:
        pipe.geometry.pose(record, query, features, pipe.scale_neighbours(best, lent))
        if lent is not None:
            shift_pose(record, lent[1])
    meta = pm.meta(best.id)
    loop = InterRobotLoop(record, req.robot, req.session, meta.robot or robot,
                          meta.session or session)  # fmt: skip
    for name in IDENTITY:
        setattr(record, name, getattr(loop, name))
    response = ScoreResponse(robot, session, req.model, req.request_id, req.robot, req.session,
                             req.query_id, best.id, best.stamp, best.pair_score, len(cands),
                             record.accepted, record.pose_status)  # fmt: skip
    return loop, response


def check_features(features: Features | None) -> Features | None:
    """The query's keyframe features of a request, checked: FleetMessageError("bad features")
    for keypoints that are not finite, beyond MAX_PIXEL px, or mostly at one spot."""
    if features is None or not len(features):
        return features
    kp = np.asarray(features.keypoints, np.float64)
    if kp.ndim != 2 or kp.shape[1] != 2 or not np.isfinite(kp).all():
        raise FleetMessageError("bad features", "keypoints are not finite [M, 2] pixels")
    if np.abs(kp).max() > MAX_PIXEL:
        raise FleetMessageError("bad features", f"keypoints beyond {MAX_PIXEL:.0e} px")
    if len(kp) >= 8 and len(np.unique(kp, axis=0)) * 2 < len(kp):
        raise FleetMessageError("bad features", "most keypoints repeat one position")
    return features


def _request_features(pipe: LoopClosurePipeline, data: bytes) -> Features | None:
    return check_features(pipe.geometry.unpack(data))
