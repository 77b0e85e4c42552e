"""`LoopClosurePipeline`: the one object that turns camera frames into loop-closure records.

The ROS node (`ros/node.py`) feeds it frame by frame; the bag replay and the map builder feed it
batches (`process_many`). Both give the same records for the same frames: frame-rate limiting
depends only on stamps, so batching the encoder changes nothing but speed.

Concurrency: a pipeline is NOT thread-safe and has no lock. One thread at a time drives it: the
replay, `build_map` and evaluation use their caller's thread; the node hands every frame and
every map service (save, load, clear, mode and parameter changes) to the one map thread of
`ros.maps.MapControl`, so a map operation falls between two frames, never inside one, and other
threads read only what that thread copied out (`MapControl.state`). A pipeline may move to
another thread between calls (the place map's SQLite connection is opened for that). The model
is only read, so two pipelines on two threads may share one (the node's background map build).

Its inputs and outputs (`Frame`, `FrameOutcome`, `PipelineCounts`) are in frames.py, its map's
life cycle (new, checked, saved, loaded, cleared) in pipeline_maps.py (`PipelineMaps`).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import replace

import numpy as np
import torch

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry.features import Features
from pair_vpr_ros.geometry.keyframes import GeometryConfig, KeyframeGeometry
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.detector import DetectorConfig, LoopDetector
from pair_vpr_ros.loops.frames import (
    Frame,
    FrameOutcome,
    PipelineCounts,
    frame_due,
    match_candidate,
)
from pair_vpr_ros.loops.growth import (
    MapGrowth,
    appearance_signature,
    live_posed_loops,
    live_scores,
    recognised_ids,
    shift_pose,
)
from pair_vpr_ros.loops.map_search import MapSearch
from pair_vpr_ros.loops.pipeline_maps import PipelineMaps
from pair_vpr_ros.loops.recency import ClockWatch
from pair_vpr_ros.loops.records import Candidate, best_record
from pair_vpr_ros.loops.rig import Rig, to_base
from pair_vpr_ros.loops.rig_frames import any_new
from pair_vpr_ros.loops.scoring import QueryDirections, dense_pair_scores, encode_for_map
from pair_vpr_ros.loops.sequence import track_of
from pair_vpr_ros.model import PairVPRModel, preprocess_batch
from pair_vpr_ros.model.decoder import default_chunk
from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap


class LoopClosurePipeline(PipelineMaps):
    """Frames -> encoder -> keyframe selection -> map query -> pair re-ranking -> LoopRecords.

    Not thread-safe: one thread at a time (see the module docstring).
    """

    def __init__(
        self,
        model: PairVPRModel,
        config: DetectorConfig | None = None,
        place_map: PlaceMap | None = None,
        index: str | IndexConfig = "flat",
        rerank_chunk: int | None = None,
        geometry: GeometryConfig | None = None,
        *,
        identity: Identity | None = None,
        prior_maps: list[PlaceMap] | None = None,
        rig: Rig | None = None,
    ) -> None:
        """identity: the robot and session of every frame (default `Identity()`). prior_maps:
        read-only maps searched with the live one (`map_search`); the pipeline closes them.
        rig: several cameras (loops/rig.py): loops posed in its base frame (`process_groups`)."""
        self.model = model
        self.detector = LoopDetector(config or DetectorConfig())
        self.index_kind = index
        self.rerank_chunk = rerank_chunk
        self.identity = identity or Identity()
        self.rig = rig
        self._place_map = place_map if place_map is not None else self._new_map()
        for checked in (self._place_map, *(prior_maps or ())):
            self._check_fingerprint(checked)
        # every map's stamps by robot-session, for recent-frame exclusion
        self.maps = MapSearch(self._place_map, prior_maps or ())
        self._clock = ClockWatch()
        self._jump_s = 0.0  # a clock jump not yet reported in an outcome
        self._last_encoded: float | None = None
        self._last_desc: dict[int, np.ndarray] = {}  # each camera's last keyframe descriptor
        self._reset_tracking()
        self.counts = PipelineCounts()
        self.geometry = KeyframeGeometry(geometry, self.counts)
        self.growth = MapGrowth()  # which keyframes the map need not store (loops/growth.py)

    # ---- state -----------------------------------------------------------------------------
    @property
    def config(self) -> DetectorConfig:
        return self.detector.config

    @property
    def place_map(self) -> PlaceMap:
        return self._place_map

    def set_config(self, config: DetectorConfig) -> None:
        self.detector.set_config(config)

    def set_mode(self, mode: str) -> None:
        """ "mapping" (query, then add each keyframe) or "localization" (query only)."""
        self.set_config(self.config.updated(mode=mode))

    def _reset_tracking(self) -> None:
        self.maps.reset(self._place_map)
        self._clock.reset()
        self.detector.reset_map()
        self._new_session()

    def _new_session(self) -> None:
        """Forget the stream so far (frame-rate limit, last keyframe, temporal consistency); the
        map keeps its keyframes, matched by stamp distance like a loaded map's."""
        self._last_encoded = None
        self._last_desc = {}
        self.detector.reset()

    # ---- processing ------------------------------------------------------------------------
    def due(self, stamp: float) -> bool:
        """Frame-rate limit: is a frame at `stamp` far enough from the last encoded one?"""
        return frame_due(stamp, self._last_encoded, self.config.min_frame_interval)

    def process(self, frame: Frame) -> FrameOutcome:
        """Run one frame through the whole pipeline."""
        return next(self.process_many([frame], batch_size=1))

    def process_many(self, frames: Iterable[Frame], batch_size: int = 8) -> Iterator[FrameOutcome]:
        """Frames in time order -> one outcome each, in the same order; the encoder runs on
        batches of up to `batch_size` due frames. A rate-limited frame that follows frames still
        waiting for the encoder waits with them, so outcome i always belongs to frame i."""
        return self.process_groups(([f] for f in frames), batch_size)

    def process_groups(
        self, groups: Iterable[list[Frame]], batch_size: int = 8
    ) -> Iterator[FrameOutcome]:
        """Rig keyframes (the frames of one instant, one per camera: `rig_frames`; a single
        camera's are single frames) in time order -> one outcome per frame, in order. A group
        shares the rate limit and the clock of its first frame, is encoded in one batch
        (batches hold whole groups, `batch_size` frames or more), is a keyframe when any of its
        frames differs from its camera's last keyframe, and shares `rerank_budget_ms`."""
        if batch_size < 1:
            raise ConfigError(f"batch size must be >= 1, got {batch_size}")
        queue: list[list[Frame | FrameOutcome]] = []  # group order; a Frame waits to encode
        waiting = 0
        for group in groups:
            stamp = group[0].stamp
            jump = self._clock.check(stamp)
            if jump:  # the frames before it finish in their session; this one starts a new one
                if queue:
                    yield from self._run_batch(queue)
                    queue, waiting = [], 0
                self.counts.clock_jumps += 1
                self._jump_s = jump
                self._new_session()
            if self.due(stamp):
                self._last_encoded = stamp
                queue.append(list(group))
                waiting += len(group)
            else:
                self.counts.rate_limited += len(group)
                queue.append([FrameOutcome(f.stamp, skipped="rate limited") for f in group])
            if waiting >= batch_size or waiting == 0:
                yield from self._run_batch(queue)
                queue, waiting = [], 0
        if queue:
            yield from self._run_batch(queue)

    def encode(self, images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 images -> dense float16 [B,N,D], descriptors float32 [B,desc_dim]."""
        return encode_for_map(self.model, preprocess_batch(images, self.model.config.image_size))

    def _run_batch(self, queue: list[list[Frame | FrameOutcome]]) -> Iterator[FrameOutcome]:
        """Encode the frames of `queue` in one batch; yield every entry's outcome in order."""
        batch = [f for group in queue for f in group if isinstance(f, Frame)]
        if batch:
            t0 = time.perf_counter()
            dense, desc = self.encode([f.rgb for f in batch])
            encode_ms = (time.perf_counter() - t0) * 1e3 / len(batch)
        i = 0
        for group in queue:
            frames = [f for f in group if isinstance(f, Frame)]
            new = bool(frames) and any_new(frames, desc[i:], self._last_desc, self.detector)
            budget, spent = self.config.rerank_budget_ms, 0.0  # a rig keyframe's, shared
            for k, entry in enumerate(group):
                if isinstance(entry, FrameOutcome):  # decided already (rate limited)
                    outcome = entry
                else:
                    if len(frames) > 1 and budget > 0:  # an even share of what is left
                        self.detector.budget_ms = max((budget - spent) / (len(frames) - k), 1e-6)
                    outcome = self._decide(entry, dense[i], desc[i], new)
                    self.detector.budget_ms = None
                    spent += outcome.timings_ms.get("rerank", 0.0)
                    i += 1
                    outcome.timings_ms["encode"] = encode_ms
                    self.counts.encoded += 1
                # a jump flushes the queue first, so the frame after it is the first entry here
                outcome.clock_jump_s, self._jump_s = self._jump_s, 0.0
                yield outcome

    def _decide(self, frame: Frame, dense, desc, new: bool) -> FrameOutcome:
        outcome = FrameOutcome(frame.stamp)
        if not new:
            self.counts.similar_to_keyframe += 1
            outcome.skipped = "similar to previous keyframe"
            return outcome
        features = None
        if self.geometry.wanted(self.config.geometric_verification):
            t0 = time.perf_counter()
            features = self.geometry.extract(frame.rgb, frame.depth, frame.camera,
                                             frame.right, frame.baseline)  # fmt: skip
            outcome.timings_ms["features"] = (time.perf_counter() - t0) * 1e3
        self._query(frame, dense, desc, outcome, features)
        decisions = outcome.decisions()
        accepted = [r for r in decisions if r.accepted]
        if accepted and self.geometry.config.relative_pose:
            outcome.timings_ms["pose"] = 0.0
            for loop in accepted:  # each with its own match's features, from its own map
                best = match_candidate(outcome, loop)
                match, lent = self.match_features(best)
                # a lent match is posed from its lender's features, camera and odometry
                near = self.scale_neighbours(best, lent)
                outcome.timings_ms["pose"] += self.geometry.pose(loop, features, match, near)
                if not loop.pose_status:  # an unposed loop is no sequence to follow (sequence.py)
                    self.detector.end_sequence(self._track(frame, best))
                if lent is not None:  # posed to the lender: T_match_query (growth.py)
                    shift_pose(loop, lent[1])
        if self.config.mode == "mapping":
            self._map_keyframe(frame, dense, desc, features, outcome)
        self._last_desc[frame.camera_id] = desc
        self.counts.keyframes += 1
        self.counts.loops += len(accepted)
        self.counts.rejected += int(bool(decisions) and not accepted)
        for loop in accepted if self.rig is not None else ():  # camera poses (growth) -> base
            to_base(loop, self.rig)
        return outcome

    def _track(self, frame: Frame, candidate: Candidate):
        """A decision's sequence track: its map's (`track_of`), with a rig its camera's too."""
        track = track_of(candidate, self.config.loop_per_map)
        return track if frame.camera_id == 0 else (frame.camera_id, track)

    def _map_keyframe(self, frame: Frame, dense, desc, features, outcome: FrameOutcome) -> None:
        """Store the keyframe (with its signature and links), or, when a stored keyframe
        represents it (`map_growth` "places", loops/growth.py), record only that."""
        who, signature = self.identity, appearance_signature(frame.rgb)
        posed = live_posed_loops(outcome)
        if self.config.map_growth == "places" and posed:
            recent = self.config.exclude_recent_s  # the detector's window, also for this
            self.growth.config = replace(self.growth.config, exclude_recent_s=recent)
            query = (frame.stamp, *self._place_map.identity(who))
            known = recognised_ids(outcome, self.config.score_threshold, self.config.global_weight)
            found = self.growth.representative(self._place_map, query, signature, posed, known)
            if found is not None:
                self.growth.represented(self._place_map, frame.stamp, who, found)
                outcome.represented_by = found[0]
                self.counts.represented += 1
                return
        meta = KeyframeMeta(
            stamp=frame.stamp, frame_id=frame.frame_id, pose=frame.pose, source=frame.source,
            robot=who.robot, session=who.session, camera=frame.camera_id,
        )  # fmt: skip
        packed = self.geometry.pack(features)
        places = self.config.map_growth == "places" and posed
        if places and self.growth.lender(self._place_map, posed) is not None:
            packed = b""  # a known place anew: a linked keyframe lends its features
        outcome.keyframe_id = self._place_map.add(desc, dense, meta, packed)
        scores = live_scores(outcome, self.config.global_weight)
        self.growth.stored(self._place_map, outcome.keyframe_id, signature, posed, scores)
        self.maps.added(replace(meta, id=outcome.keyframe_id))
        pending = self._place_map.index_diagnostics.get("map_keyframes_pending", 0)
        self.counts.map_keyframes_pending = pending
        for loop in outcome.decisions():
            loop.query_id = outcome.keyframe_id

    def _query(
        self, frame: Frame, dense, desc, outcome: FrameOutcome, features: Features | None
    ) -> None:
        """Search, re-rank and decide: `outcome.loop` (and, with `loop_per_map` and prior
        maps, `outcome.loops`: one decision per map), `outcome.candidates` (all maps')."""
        timings = outcome.timings_ms
        t0 = time.perf_counter()
        who = self.identity
        groups = self._search_groups(desc, frame.stamp)
        if groups is None:
            return
        timings["search"] = (time.perf_counter() - t0) * 1e3
        outcome.candidates = sorted((c for g in groups for c in g), key=lambda c: c.rank_before)

        def rerank(cands: list[Candidate]) -> np.ndarray:  # called once per step with a budget
            t1 = time.perf_counter()
            if all(c.prior < 0 for c in cands):  # the live map only: as before prior maps
                scores = self.pair_scores(dense, [c.id for c in cands])
            else:  # each candidate scored with its own map's dense tokens
                stored = self.maps.dense(cands)
                scores = dense_pair_scores(self.model, dense, stored, self.rerank_chunk)
            timings["rerank"] = timings.get("rerank", 0.0) + (time.perf_counter() - t1) * 1e3
            return scores

        directions = QueryDirections(self.model, dense)

        def one_way(cands: list[Candidate], first: str) -> np.ndarray:  # the re-rank cascade
            t1 = time.perf_counter()
            logits = directions.logits(self.maps.dense(cands), first)
            timings["rerank"] = timings.get("rerank", 0.0) + (time.perf_counter() - t1) * 1e3
            return logits

        def verify(match: Candidate) -> tuple[int, float]:
            stored, lent = self.match_features(match)
            inliers, ratio, points = self.geometry.verify_points(features, stored)
            if lent is None:  # lent features are another image's points: not drawn
                outcome.matches[match.rank_before] = points
            return inliers, ratio

        # A back end compiled for a fixed chunk (OpenVINO) pads shorter calls: whole chunks.
        fixed = getattr(self.model, "chunk_size", None)
        step = fixed or self.rerank_chunk or default_chunk(torch.device(self.model.device))
        cascade = self.config.rerank_cascade and QueryDirections.supported(self.model)
        records = []
        for candidates in groups:  # one group (all maps together) unless loop_per_map
            record = self.detector.decide(  # the cascade: a candidate and a direction a step
                frame.stamp, frame.frame_id, candidates, rerank, verify,
                step=1 if cascade else step, first=1 if cascade else fixed or 1,
                query_identity=(who.robot, who.session),
                track=self._track(frame, candidates[0]),
                one_way=one_way if cascade else None,
            )  # fmt: skip
            if record is not None:
                record.query_camera = frame.camera_id
                self.counts.decided(record.scored, self.detector)
                records.append(record)
        outcome.loop = best_record(records, self.config.global_weight)
        outcome.loops = records if len(records) > 1 else []
