"""The map's growth policy: a keyframe whose place and appearance the map already holds is not
stored again (docs/map-storage.md, growth).

Each keyframe gets an appearance signature (`appearance_signature`: per cell of a coarse grid,
each channel's mean and spread; lighting, season and a large change of view change it, the
place's identity and small image noise hardly do). A stored keyframe keeps its signature and a
link to every keyframe it closed a loop with under a confident relative pose. A new keyframe Q
with such a loop to K is *represented* when K or a keyframe linked to K (one hop: the demo model
finds revisits in another lighting far better than in the same one, so a day query often lands
on a dusk keyframe whose day twin is linked to it) lies within `max_translation_m` and
`max_rotation_deg` of Q (the loop's pose, composed with the link's) and its signature within
`max_appearance` of Q's, and Q's re-ranking scored it at or above the detector's threshold on
its own (`recognised_ids`: a loop accepted only through `sequence_margin` is a view the model
barely knows from its match; represented by it, the place would be found again only inside a
sequence, and a later query arriving there cold would miss it). A represented keyframe is not
stored (no dense tokens, features or index entry), only a row naming its representative; its
loops are published as found.

A keyframe that is not represented but has such a loop to a stored keyframe with features
within the (wider) share limits is a known place in another light or from another view: it is
stored, its descriptor and dense tokens with it, but without features. A loop found to it is
verified and posed with the features of its nearest linked keyframe that has them
(`feature_source`), and the pose composed with the link's (`shift_pose`), so the loop still
names it and its pose is T_it_query.
"""

from __future__ import annotations

import math

import numpy as np

from pair_vpr_ros.geometry.epipolar import skew
from pair_vpr_ros.geometry.rotations import quaternion_matrix
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.frames import FrameOutcome, match_candidate
from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.place_map.growth.policy import GrowthConfig, find_representative, is_recent
from pair_vpr_ros.place_map.growth.tables import Represented, compose, invert

GRID = 4  # cells a side of the signature's grid: 4 x 4 x 3 channels x (mean, spread) = 96
CONFIDENT = ("metric", "metric-odometry")  # pose kinds a link or a representation may use


def appearance_signature(rgb: np.ndarray) -> np.ndarray:
    """RGB uint8 [H, W, 3] -> [2 x G x G x 3] float32 in [0, 1]: each grid cell's per-channel
    mean, then its per-channel standard deviation (G = GRID, fewer for a tiny image)."""
    img = np.asarray(rgb, dtype=np.float32) / 255.0
    g = max(1, min(GRID, img.shape[0], img.shape[1]))
    rows = np.linspace(0, img.shape[0], g + 1).astype(int)
    cols = np.linspace(0, img.shape[1], g + 1).astype(int)
    cells = [img[rows[i] : rows[i + 1], cols[j] : cols[j + 1]].reshape(-1, img.shape[2])
             for i in range(g) for j in range(g)]  # fmt: skip
    mean = np.stack([c.mean(axis=0) for c in cells])
    spread = np.stack([c.std(axis=0) for c in cells])
    return np.concatenate([mean.ravel(), spread.ravel()]).astype(np.float32)


def pose_of(record: LoopRecord) -> tuple[float, ...] | None:
    """T_match_query of an accepted loop with a confident pose (x y z qx qy qz qw), else None."""
    pose = (record.tx, record.ty, record.tz, record.qx, record.qy, record.qz, record.qw)
    ok = record.accepted and record.pose_status in CONFIDENT
    return pose if ok and all(math.isfinite(v) for v in pose) else None


def live_posed_loops(outcome: FrameOutcome) -> list[tuple[int, tuple[float, ...]]]:
    """(match id, T_match_query) of the outcome's accepted loops into the live map (not a prior
    map) with a confident pose."""
    out = []
    for record in outcome.decisions():
        pose, match = pose_of(record), match_candidate(outcome, record)
        if pose is not None and match is not None and match.prior < 0:
            out.append((record.match_id, pose))
    return out


def live_scores(outcome: FrameOutcome, global_weight: float) -> dict[int, float]:
    """{id: re-rank score (pair score + global_weight x global similarity; NaN: not scored)} of
    the outcome's live-map candidates: a stored keyframe's links keep them (compact's rule)."""
    return {c.id: c.rerank_score(global_weight) for c in outcome.candidates if c.prior < 0}


def recognised_ids(outcome: FrameOutcome, threshold: float, global_weight: float) -> set[int]:
    """Live-map keyframes that the outcome's re-ranking scored at or above `threshold` on their
    own (re-rank score: pair score + global_weight x global similarity; unscored ones are not):
    only these may represent the query (module docstring)."""
    scores = live_scores(outcome, global_weight)
    return {kf_id for kf_id, score in scores.items() if score >= threshold}


class MapGrowth:
    """The policy's decisions and the rows it records in one map (`PlaceMap.growth`)."""

    def __init__(self, config: GrowthConfig | None = None) -> None:
        self.config = config or GrowthConfig()

    def representative(
        self,
        place_map: PlaceMap,
        query: tuple[float, str, str],
        signature: np.ndarray,
        posed: list[tuple[int, tuple]],
        recognised: set[int] | None = None,
    ) -> tuple[int, float] | None:
        """(id, signature distance) of the stored keyframe that represents a new one (`query`:
        stamp, robot, session) with `signature` [S] and loops `posed` ((match id,
        T_match_query) each), None: no such. `recognised`: the only keyframes that may
        (`recognised_ids`); None: any."""
        tables = place_map.growth

        def signature_of(kf_id: int) -> np.ndarray | None:
            if recognised is not None and kf_id not in recognised:
                return None
            meta = place_map.meta(kf_id)
            if is_recent(query, (meta.stamp, *place_map.identity(meta)), self.config):
                return None
            return tables.signature(kf_id)

        return find_representative(signature, posed, tables.links, signature_of, self.config)

    def lender(self, place_map: PlaceMap, posed: list[tuple[int, tuple]]) -> int | None:
        """The stored keyframe with features, one of the loops `posed` ((match id,
        T_match_query) each) within the share limits, that lends a new keyframe its features
        (module docstring); None: the new keyframe keeps its own."""
        for match_id, t_match_query in posed:
            if self.config.shares(t_match_query) and place_map.features(match_id):
                return match_id
        return None

    def feature_source(self, place_map: PlaceMap, kf_id: int) -> tuple[int, tuple] | None:
        """(id, T_kf_source) of the keyframe whose features serve `kf_id`, stored without its
        own: the nearest linked keyframe with features within the share limits; None: none."""
        best = None
        for other, t_other_kf in place_map.growth.links(kf_id):
            if self.config.shares(t_other_kf) and place_map.features(other):
                distance = math.dist(t_other_kf[:3], (0.0, 0.0, 0.0))
                if best is None or distance < best[0]:
                    best = (distance, other, invert(t_other_kf))
        return None if best is None else (best[1], best[2])

    def stored(
        self, place_map: PlaceMap, kf_id: int, signature: np.ndarray, posed: list[tuple],
        scores: dict[int, float] | None = None,
    ) -> None:  # fmt: skip
        """Record a stored keyframe's signature and its links (one per posed loop), each with
        the re-rank score its query gave the match (`scores`, `live_scores`)."""
        tables, scores = place_map.growth, scores or {}
        tables.add_signature(kf_id, signature)
        for match_id, t_match_query in posed:
            if match_id != kf_id:
                tables.add_link(kf_id, match_id, t_match_query, scores.get(match_id))

    @staticmethod
    def represented(
        place_map: PlaceMap, stamp: float, who: Identity, found: tuple[int, float]
    ) -> None:
        row = Represented(float(stamp), who.robot, who.session, int(found[0]), float(found[1]))
        place_map.growth.add_represented(row)


def shift_pose(record: LoopRecord, t_match_source: tuple[float, ...]) -> None:
    """A loop posed with the features of the match's feature source (T_source_query) ->
    T_match_query = T_match_source T_source_query. A scale-free pose has no translation to
    compose: the record keeps no pose then, and says why. The covariance (`lent_covariance`)
    is turned into the match's frame, and the link's own error added."""
    pose = pose_of(record)
    if pose is None:
        if record.pose_status:
            record.pose_status, record.tx, record.ty, record.tz = "", *(math.nan,) * 3
            record.qx, record.qy, record.qz, record.qw = (math.nan,) * 4
            record.covariance = ()
            record.pose_reason = "scale-free pose to the features of a linked keyframe"
        return
    shifted = compose(t_match_source, pose)
    record.tx, record.ty, record.tz, record.qx, record.qy, record.qz, record.qw = shifted
    if len(record.covariance) == 36:
        cov = np.asarray(record.covariance, np.float64).reshape(6, 6)
        cov = lent_covariance(cov, quaternion_matrix(t_match_source[3:7]), np.asarray(pose[:3]))
        record.covariance = tuple(float(v) for v in cov.ravel())


def lent_covariance(cov: np.ndarray, r_link: np.ndarray, t: np.ndarray) -> np.ndarray:
    """cov [6, 6] of T_source_query (d_t, d_rot along the source camera's axes, covariance.py)
    -> that of T_match_query = T_match_source T_source_query, with r_link [3, 3] the link's
    rotation and t [3] T_source_query's translation. The loop's error turns with the link:
    B cov B^T, B = diag(R_link, R_link). The link is a loop between views of the same place
    like this one, and its covariance is not stored: its error is taken as the loop's own,
    entering as d_t = e_t - [R_link t]x e_rot, d_rot = e_rot."""
    b = np.zeros((6, 6))
    b[:3, :3] = b[3:, 3:] = r_link
    turned = b @ cov @ b.T
    lever = np.eye(6)
    lever[:3, 3:] = -skew(r_link @ t)
    out = turned + lever @ turned @ lever.T
    return (out + out.T) / 2
