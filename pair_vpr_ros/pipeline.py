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
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from pair_vpr_ros.detector import Candidate, DetectorConfig, LoopDetector, LoopRecord
from pair_vpr_ros.errors import ConfigError, MapFingerprintError, MapUnavailableError
from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.geometry.features import Features
from pair_vpr_ros.geometry.keyframes import GeometryConfig, KeyframeGeometry
from pair_vpr_ros.geometry.odometry_scale import Neighbour
from pair_vpr_ros.identity import LEGACY_SESSION, Identity
from pair_vpr_ros.map_search import MapSearch
from pair_vpr_ros.model import PairVPRModel, preprocess_batch
from pair_vpr_ros.model.decoder import default_chunk
from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.prior_maps import refuse_prior_target
from pair_vpr_ros.recency import ClockWatch
from pair_vpr_ros.scoring import dense_pair_scores, encode_for_map, map_pair_scores
from pair_vpr_ros.types import Pose


@dataclass
class Frame:
    """One camera frame: RGB uint8 [H,W,3], header stamp in seconds, optional pose
    (x, y, z, qx, qy, qz, qw), optional aligned depth [H,W] float32 metres (NaN / 0: none) and
    the camera's intrinsics (needed for a relative pose); stereo: the rectified right image
    [H,W,3] and the baseline (m), keyframes without depth get it from them (geometry/stereo.py)."""

    stamp: float
    rgb: np.ndarray
    frame_id: str = ""
    pose: Pose | None = None
    source: str = ""
    depth: np.ndarray | None = None
    camera: CameraModel | None = None
    right: np.ndarray | None = None
    baseline: float = 0.0


@dataclass
class FrameOutcome:
    stamp: float
    keyframe_id: int | None = None  # id in the map when the frame was added
    skipped: str = ""  # why the frame was not a keyframe ("" when it was)
    loop: LoopRecord | None = None  # the best candidate after re-ranking, accepted or not
    # Candidates in global (FAISS) order with their pair scores: [0] is what ranking by global
    # similarity alone would return.
    candidates: list[Candidate] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)
    # > 0: the stamps jumped back this many seconds before this frame, which starts a session
    clock_jump_s: float = 0.0


@dataclass
class PipelineCounts:
    """What a pipeline did with its frames since it was made. The node's `/diagnostics` and
    the replay's `summary.json` (`pipeline_counts`) report these names."""

    rate_limited: int = 0  # skipped unencoded: closer than min_frame_interval to the last one
    encoded: int = 0
    similar_to_keyframe: int = 0  # encoded, but too similar to the last keyframe
    keyframes: int = 0
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
    rerank_budget_cut: int = 0  # keyframes whose re-ranking stopped at rerank_budget_ms
    clock_jumps: int = 0  # stamps that went back by more than CLOCK_JUMP_S: new sessions
    stereo_depth: int = 0  # keyframes whose depth came from the stereo pair
    stereo_invalid: int = 0  # keyframes whose stereo pair could not give depth (unrectified..)
    map_searches_skipped: int = 0  # keyframes not queried: the map's Milvus did not answer
    map_keyframes_pending: int = 0  # now: keyframes kept until the map's Milvus answers again

    def to_dict(self) -> dict[str, int]:
        return asdict(self)


class LoopClosurePipeline:
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
    ) -> None:
        """identity: the robot and session of every frame (default `Identity()`). prior_maps:
        read-only maps searched with the live one (`map_search`); the pipeline closes them."""
        self.model = model
        self.detector = LoopDetector(config or DetectorConfig())
        self.index_kind = index
        self.rerank_chunk = rerank_chunk
        self.identity = identity or Identity()
        self._place_map = place_map if place_map is not None else self._new_map()
        for checked in (self._place_map, *(prior_maps or ())):
            self._check_fingerprint(checked)
        # every map's stamps by robot-session, for recent-frame exclusion
        self.maps = MapSearch(self._place_map, prior_maps or ())
        self._clock = ClockWatch()
        self._jump_s = 0.0  # a clock jump not yet reported in an outcome
        self._last_encoded: float | None = None
        self._last_desc: np.ndarray | None = None
        self._reset_tracking()
        self.counts = PipelineCounts()
        self.geometry = KeyframeGeometry(geometry, self.counts)

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

    def _new_map(self) -> PlaceMap:
        desc_dim, dense_shape = self._new_map_shapes()
        return PlaceMap(
            desc_dim=desc_dim,
            dense_shape=dense_shape,
            fingerprint=self.model.fingerprint,
            index=self.index_kind,
        )

    def _check_fingerprint(self, place_map: PlaceMap) -> None:
        if place_map.fingerprint != self.model.fingerprint:
            raise MapFingerprintError(
                f"the map was built with model {place_map.fingerprint!r} but this pipeline runs "
                f"{self.model.fingerprint!r}: use the same weights and image size, or rebuild it"
            )
        want = self._new_map_shapes()
        if (place_map.desc_dim, place_map.dense_shape) != want:
            raise MapFingerprintError(
                f"the map holds descriptors of {place_map.desc_dim} and dense tokens of "
                f"{list(place_map.dense_shape)}, this model makes {want[0]} and {list(want[1])} "
                "(its manifest was edited?): rebuild the map with this model"
            )

    def _new_map_shapes(self) -> tuple[int, tuple[int, int]]:
        cfg = self.model.config
        return cfg.desc_dim, (self.model.num_patches, cfg.embed_dim)

    def _reset_tracking(self) -> None:
        self.maps.reset(self._place_map)
        self._clock.reset()
        self._new_session()

    def _new_session(self) -> None:
        """Forget the stream so far (frame-rate limit, last keyframe, temporal consistency); the
        map keeps its keyframes, matched by stamp distance like a loaded map's."""
        self._last_encoded = None
        self._last_desc = None
        self.detector.reset()

    def save_map(self, directory: str | Path, overwrite: bool = False) -> Path:
        refuse_prior_target(directory, self.maps.priors)  # a prior map is never written
        return self._place_map.save(directory, overwrite=overwrite)

    def load_map(self, directory: str | Path) -> int:
        """Replace the map by a saved one (same model required); returns its keyframe count.

        Reloading the folder the current map was saved to discards its unsaved keyframes (the
        folder is locked by the current map, so that one is closed first)."""
        refuse_prior_target(directory, self.maps.priors)  # it is searched already, read-only
        current = self._place_map
        same = current.directory is not None and current.directory == Path(directory).resolve()
        if same:
            current.close()
        loaded = None
        try:
            loaded = PlaceMap.load(
                directory, expected_fingerprint=self.model.fingerprint,
                legacy_identity=(self.identity.robot, LEGACY_SESSION),
            )  # fmt: skip
            self._check_fingerprint(loaded)
        except Exception:
            if loaded is not None:
                loaded.close()
            if same:  # the old map is gone: continue on an empty one rather than none
                self._place_map = self._new_map()
                self._reset_tracking()
            raise
        self._place_map = loaded
        self._reset_tracking()
        if not same:
            current.close()
        return len(loaded)

    def clear_map(self) -> None:
        self._place_map.clear()
        self._reset_tracking()

    def close(self) -> None:
        self._place_map.close()
        self.maps.close_priors()

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
        if batch_size < 1:
            raise ConfigError(f"batch size must be >= 1, got {batch_size}")
        queue: list[Frame | FrameOutcome] = []  # frame order; a Frame waits for the encoder
        waiting = 0
        for frame in frames:
            jump = self._clock.check(frame.stamp)
            if jump:  # the frames before it finish in their session; this one starts a new one
                if queue:
                    yield from self._run_batch(queue)
                    queue, waiting = [], 0
                self.counts.clock_jumps += 1
                self._jump_s = jump
                self._new_session()
            if self.due(frame.stamp):
                self._last_encoded = frame.stamp
                queue.append(frame)
                waiting += 1
            else:
                self.counts.rate_limited += 1
                queue.append(FrameOutcome(frame.stamp, skipped="rate limited"))
            if waiting >= batch_size or waiting == 0:
                yield from self._run_batch(queue)
                queue, waiting = [], 0
        if queue:
            yield from self._run_batch(queue)

    def encode(self, images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 images -> dense float16 [B,N,D], descriptors float32 [B,desc_dim]."""
        return encode_for_map(self.model, preprocess_batch(images, self.model.config.image_size))

    def _run_batch(self, queue: list[Frame | FrameOutcome]) -> Iterator[FrameOutcome]:
        """Encode the frames of `queue` in one batch; yield every entry's outcome in order."""
        batch = [f for f in queue if isinstance(f, Frame)]
        if batch:
            t0 = time.perf_counter()
            dense, desc = self.encode([f.rgb for f in batch])
            encode_ms = (time.perf_counter() - t0) * 1e3 / len(batch)
        i = 0
        for entry in queue:
            if isinstance(entry, FrameOutcome):  # decided already (rate limited)
                outcome = entry
            else:
                outcome = self._decide(entry, dense[i], desc[i])
                i += 1
                outcome.timings_ms["encode"] = encode_ms
                self.counts.encoded += 1
            # a jump flushes the queue first, so the frame after it is the first entry here
            outcome.clock_jump_s, self._jump_s = self._jump_s, 0.0
            yield outcome

    def _decide(self, frame: Frame, dense: np.ndarray, desc: np.ndarray) -> FrameOutcome:
        outcome = FrameOutcome(frame.stamp)
        last = self._last_desc
        if not self.detector.is_new_keyframe(None if last is None else float(desc @ last)):
            self.counts.similar_to_keyframe += 1
            outcome.skipped = "similar to previous keyframe"
            return outcome
        features = None
        if self.geometry.wanted(self.config.geometric_verification):
            t0 = time.perf_counter()
            features = self.geometry.extract(frame.rgb, frame.depth, frame.camera,
                                             frame.right, frame.baseline)  # fmt: skip
            outcome.timings_ms["features"] = (time.perf_counter() - t0) * 1e3
        outcome.loop = self._query(frame, dense, desc, outcome, features)
        loop = outcome.loop
        if loop is not None and loop.accepted and self.geometry.config.relative_pose:
            best = match_candidate(outcome)
            match = self._stored_features(best)
            near = self._scale_neighbours(best)
            outcome.timings_ms["pose"] = self.geometry.pose(loop, features, match, near)
        if self.config.mode == "mapping":
            who = self.identity
            meta = KeyframeMeta(
                stamp=frame.stamp, frame_id=frame.frame_id, pose=frame.pose, source=frame.source,
                robot=who.robot, session=who.session,
            )  # fmt: skip
            packed = self.geometry.pack(features)
            outcome.keyframe_id = self._place_map.add(desc, dense, meta, packed)
            self.maps.added(replace(meta, id=outcome.keyframe_id))
            pending = self._place_map.index_diagnostics.get("map_keyframes_pending", 0)
            self.counts.map_keyframes_pending = pending
            if outcome.loop is not None:
                outcome.loop.query_id = outcome.keyframe_id
        self._last_desc = desc
        self.counts.keyframes += 1
        if outcome.loop is not None and outcome.loop.accepted:
            self.counts.loops += 1
        elif outcome.loop is not None:
            self.counts.rejected += 1
        return outcome

    def _query(self, frame: Frame, dense, desc, outcome: FrameOutcome, features: Features | None):
        timings = outcome.timings_ms
        t0 = time.perf_counter()
        try:
            found = self.maps.search(desc, frame.stamp, self.identity, self.config)
        except MapUnavailableError:  # logged by the map once per outage; nothing is lost
            self.counts.map_searches_skipped += 1
            return None
        if found is None:
            return None
        timings["search"] = (time.perf_counter() - t0) * 1e3
        outcome.candidates = candidates = found

        def rerank(cands: list[Candidate]) -> np.ndarray:  # called once per step with a budget
            t1 = time.perf_counter()
            if all(c.prior < 0 for c in cands):  # the live map only: as before prior maps
                scores = self.pair_scores(dense, [c.id for c in cands])
            else:  # each candidate scored with its own map's dense tokens
                stored = self.maps.dense(cands)
                scores = dense_pair_scores(self.model, dense, stored, self.rerank_chunk)
            timings["rerank"] = timings.get("rerank", 0.0) + (time.perf_counter() - t1) * 1e3
            return scores

        def verify(match: Candidate) -> tuple[int, float]:
            return self.geometry.verify(features, self._stored_features(match))

        # A back end compiled for a fixed chunk (OpenVINO) pads shorter calls: whole chunks.
        fixed = getattr(self.model, "chunk_size", None)
        step = fixed or self.rerank_chunk or default_chunk(torch.device(self.model.device))
        record = self.detector.decide(
            frame.stamp, frame.frame_id, candidates, rerank, verify, step=step, first=fixed or 1,
            query_identity=(self.identity.robot, self.identity.session),
        )  # fmt: skip
        if record is not None:
            self.counts.candidates_scored += record.scored
            self.counts.rerank_budget_cut += int(0 < record.scored < record.candidates)
        return record

    def _stored_features(self, match: Candidate) -> Features | None:
        return self.geometry.unpack(self.maps.map_of(match).features(match.id))

    def _scale_neighbours(self, match: Candidate) -> list[Neighbour]:
        """Keyframes recorded next to the match, with an odometry baseline, for the scale of a
        monocular loop (`MapSearch.near`)."""
        meta, near = self.maps.near(match, self.geometry.config.pose.scale_neighbours)
        load = lambda i: self._stored_features(replace(match, id=i))  # noqa: E731
        return self.geometry.neighbours(meta, near, load)

    def match_meta(self, outcome: FrameOutcome) -> KeyframeMeta | None:
        """The metadata of the outcome's loop match, from whichever map holds it."""
        best = match_candidate(outcome)
        return None if best is None else self.maps.map_of(best).meta(best.id)

    def pair_scores(self, dense: np.ndarray, ids: list[int]) -> np.ndarray:
        """Query dense [N,D] against map keyframes `ids` -> bidirectional scores [K]."""
        return map_pair_scores(self.model, self._place_map, dense, ids, self.rerank_chunk)


def match_candidate(outcome: FrameOutcome) -> Candidate | None:
    """The candidate an outcome's loop record names (its rank before re-ranking is unique)."""
    loop = outcome.loop
    if loop is None:
        return None
    return next(c for c in outcome.candidates if c.rank_before == loop.rank_before)


def frame_due(stamp: float, last: float | None, interval: float) -> bool:
    """The frame-rate limit: is a frame at `stamp` (s) at least `interval` s from the last one
    let through, at `last` (None: none yet)? The pipeline asks it before encoding; the node
    asks it before queueing, so frames the pipeline would skip never wait in its queue."""
    return last is None or abs(stamp - last) >= interval
