"""What goes into the pipeline and what comes out: `Frame` (one camera frame), `FrameOutcome`
(what became of it), `PipelineCounts` (the totals), the frame-rate rule `frame_due` and
`match_candidate`. The pipeline itself is `pipeline.LoopClosurePipeline`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.loops.records import Candidate, LoopRecord
from pair_vpr_ros.types import Pose


@dataclass
class Frame:
    """One camera frame: RGB uint8 [H,W,3], header stamp in seconds, optional pose
    (x, y, z, qx, qy, qz, qw), optional aligned depth [H,W] float32 metres (NaN / 0: none) and
    the camera's intrinsics (needed for a relative pose); stereo: the rectified right image
    [H,W,3] and the baseline (m), keyframes without depth get it from them (geometry/stereo.py);
    camera_id: the camera's index in a rig (loops/rig.py; 0: the only camera)."""

    stamp: float
    rgb: np.ndarray
    frame_id: str = ""
    pose: Pose | None = None
    source: str = ""
    depth: np.ndarray | None = None
    camera: CameraModel | None = None
    right: np.ndarray | None = None
    baseline: float = 0.0
    camera_id: int = 0


@dataclass
class FrameOutcome:
    stamp: float
    keyframe_id: int | None = None  # id in the map when the frame was added
    represented_by: int | None = None  # mapping, not added: the stored keyframe representing it
    skipped: str = ""  # why the frame was not a keyframe ("" when it was)
    loop: LoopRecord | None = None  # the best candidate after re-ranking, accepted or not
    # loop_per_map: one decision per map searched (live map first), `loop` the best of them
    # (accepted first, then by re-rank score); empty: `loop` is the only one
    loops: list[LoopRecord] = field(default_factory=list)
    # Candidates in global (FAISS) order with their pair scores: [0] is what ranking by global
    # similarity alone would return.
    candidates: list[Candidate] = field(default_factory=list)
    # Geometric verification's inlier matches, by the verified candidate's rank_before: [I, 4]
    # float32 (x, y in the query image, x, y in the match image); what loop images draw. Only
    # candidates verified on their own features (not features a linked keyframe lends).
    matches: dict[int, np.ndarray] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)
    # > 0: the stamps jumped back this many seconds before this frame, which starts a session
    clock_jump_s: float = 0.0

    def decisions(self) -> list[LoopRecord]:
        """Every decision made for this frame: `loops`, else `loop` alone, else none."""
        return self.loops or ([self.loop] if self.loop is not None else [])

    def reported(self) -> list[LoopRecord]:
        """The records to publish or write: every accepted loop (at most one per map), else the
        best rejected decision (`loop`), else none."""
        accepted = [r for r in self.decisions() if r.accepted]
        return accepted or ([self.loop] if self.loop is not None else [])


@dataclass
class PipelineCounts:
    """What a pipeline did with its frames since it was made. The node's `/diagnostics` and
    the replay's `summary.json` (`pipeline_counts`) report these names."""

    rate_limited: int = 0  # skipped unencoded: closer than min_frame_interval to the last one
    encoded: int = 0
    similar_to_keyframe: int = 0  # encoded, but too similar to the last keyframe
    keyframes: int = 0
    represented: int = 0  # keyframes not stored: a stored one represents them (map_growth)
    loops: int = 0  # accepted loop closures
    rejected: int = 0  # keyframes whose best candidate was not accepted
    pose_metric: int = 0  # accepted loops with a metric relative pose (depth)
    pose_metric_odometry: int = 0  # ... metric, monocular, scaled by an odometry baseline
    pose_scale_free: int = 0  # ... with a rotation and a translation direction only
    pose_none: int = 0  # ... without a pose (the record's pose_reason says why)
    depth_wrong_size: int = 0  # keyframes whose depth image did not fit (dropped)
    intrinsics_wrong_size: int = 0  # keyframes whose intrinsics were for another size
    features_damaged: int = 0  # stored features that could not be unpacked
    candidates_scored: int = 0  # pair scores computed (candidates re-ranked, all keyframes)
    decoder_passes: int = 0  # pair decoder runs: one direction of one pair each (full: 2 a pair)
    rerank_budget_cut: int = 0  # keyframes whose re-ranking stopped at rerank_budget_ms
    rerank_skipped: int = 0  # keyframes not re-ranked: best below global_floor / learned floor
    rerank_covered: int = 0  # keyframes whose every candidate got at least one direction
    clock_jumps: int = 0  # stamps that went back by more than CLOCK_JUMP_S: new sessions
    stereo_depth: int = 0  # keyframes whose depth came from the stereo pair
    stereo_invalid: int = 0  # keyframes whose stereo pair could not give depth (unrectified..)
    map_searches_skipped: int = 0  # keyframes not queried: the map's Milvus did not answer
    map_keyframes_pending: int = 0  # now: keyframes kept until the map's Milvus answers again

    def decided(self, scored: int, detector) -> None:
        """Count one decision's re-rank work: `scored` candidates, and the `LoopDetector`'s
        account of its last `decide` (passes, budget cut, skipped, covered)."""
        self.candidates_scored += scored
        self.decoder_passes += detector.last_passes
        self.rerank_budget_cut += int(detector.last_cut)
        self.rerank_skipped += int(detector.last_skipped)
        self.rerank_covered += int(detector.last_covered)

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


def match_candidate(outcome: FrameOutcome, loop: LoopRecord | None = None) -> Candidate | None:
    """The candidate a loop record of the outcome names (default: `outcome.loop`); its rank
    before re-ranking is unique among the outcome's candidates, whichever map they come from."""
    loop = outcome.loop if loop is None else loop
    if loop is None:
        return None
    return next(c for c in outcome.candidates if c.rank_before == loop.rank_before)


def frame_due(stamp: float, last: float | None, interval: float) -> bool:
    """The frame-rate limit: is a frame at `stamp` (s) at least `interval` s from the last one
    let through, at `last` (None: none yet)? The pipeline asks it before encoding; the node
    asks it before queueing, so frames the pipeline would skip never wait in its queue."""
    return last is None or abs(stamp - last) >= interval
