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
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from pair_vpr_ros.detector import Candidate, DetectorConfig, LoopDetector, LoopRecord
from pair_vpr_ros.errors import ConfigError, MapFingerprintError
from pair_vpr_ros.geometry.camera import CameraModel
from pair_vpr_ros.geometry.features import Features
from pair_vpr_ros.geometry.keyframes import GeometryConfig, KeyframeGeometry
from pair_vpr_ros.geometry.odometry_scale import Neighbour
from pair_vpr_ros.model import PairVPRModel, preprocess_batch
from pair_vpr_ros.model.decoder import default_chunk
from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap
from pair_vpr_ros.recency import ClockWatch, StampBuffer
from pair_vpr_ros.types import Pose


@dataclass
class Frame:
    """One camera frame: RGB uint8 [H,W,3], header stamp in seconds, optional pose
    (x, y, z, qx, qy, qz, qw), optional aligned depth [H,W] float32 metres (NaN / 0: none) and
    the camera's intrinsics (needed for a relative pose)."""

    stamp: float
    rgb: np.ndarray
    frame_id: str = ""
    pose: Pose | None = None
    source: str = ""
    depth: np.ndarray | None = None
    camera: CameraModel | None = None


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
        index: str = "flat",
        rerank_chunk: int | None = None,
        geometry: GeometryConfig | None = None,
    ) -> None:
        self.model = model
        self.detector = LoopDetector(config or DetectorConfig())
        self.index_kind = index
        self.rerank_chunk = rerank_chunk
        self._place_map = place_map if place_map is not None else self._new_map()
        self._check_fingerprint(self._place_map)
        self._stamps = StampBuffer()  # keyframe stamps by id, for recent-frame exclusion
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
        self._stamps = StampBuffer(m.stamp for m in self._place_map.all_meta())
        self._clock.reset()
        self._new_session()

    def _new_session(self) -> None:
        """Forget the stream so far (frame-rate limit, last keyframe, temporal consistency); the
        map keeps its keyframes, matched by stamp distance like a loaded map's."""
        self._last_encoded = None
        self._last_desc = None
        self.detector.reset()

    def save_map(self, directory: str | Path) -> Path:
        return self._place_map.save(directory)

    def load_map(self, directory: str | Path) -> int:
        """Replace the map by a saved one (same model required); returns its keyframe count.

        Reloading the folder the current map was saved to discards its unsaved keyframes (the
        folder is locked by the current map, so that one is closed first)."""
        current = self._place_map
        same = current.directory is not None and current.directory == Path(directory).resolve()
        if same:
            current.close()
        loaded = None
        try:
            loaded = PlaceMap.load(directory, expected_fingerprint=self.model.fingerprint)
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
            features = self.geometry.extract(frame.rgb, frame.depth, frame.camera)
            outcome.timings_ms["features"] = (time.perf_counter() - t0) * 1e3
        outcome.loop = self._query(frame, dense, desc, outcome, features)
        loop = outcome.loop
        if loop is not None and loop.accepted and self.geometry.config.relative_pose:
            match = self._stored_features(loop.match_id)
            near = self._scale_neighbours(loop.match_id)
            outcome.timings_ms["pose"] = self.geometry.pose(loop, features, match, near)
        if self.config.mode == "mapping":
            meta = KeyframeMeta(
                stamp=frame.stamp, frame_id=frame.frame_id, pose=frame.pose, source=frame.source
            )
            packed = self.geometry.pack(features)
            outcome.keyframe_id = self._place_map.add(desc, dense, meta, packed)
            self._stamps.append(frame.stamp)
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
        c = self.config
        allowed = self._stamps.eligible(
            frame.stamp, c.exclude_recent_s, c.exclude_recent_keyframes
        )
        if allowed is None:
            return None
        timings = outcome.timings_ms
        t0 = time.perf_counter()
        if isinstance(allowed, int):  # ids below it: a prefix
            hits = self._place_map.search(desc, c.top_k, max_id=allowed - 1)
        else:
            hits = self._place_map.search(desc, c.top_k, allowed=allowed)
        timings["search"] = (time.perf_counter() - t0) * 1e3
        outcome.candidates = candidates = [
            self._candidate(kf_id, sim, rank) for rank, (kf_id, sim) in enumerate(hits, start=1)
        ]

        def rerank(cands: list[Candidate]) -> np.ndarray:  # called once per step with a budget
            t1 = time.perf_counter()
            scores = self.pair_scores(dense, [c.id for c in cands])
            timings["rerank"] = timings.get("rerank", 0.0) + (time.perf_counter() - t1) * 1e3
            return scores

        def verify(match_id: int) -> tuple[int, float]:
            return self.geometry.verify(features, self._stored_features(match_id))

        # A back end compiled for a fixed chunk (OpenVINO) pads shorter calls: whole chunks.
        fixed = getattr(self.model, "chunk_size", None)
        step = fixed or self.rerank_chunk or default_chunk(torch.device(self.model.device))
        record = self.detector.decide(
            frame.stamp, frame.frame_id, candidates, rerank, verify, step=step, first=fixed or 1
        )
        if record is not None:
            self.counts.candidates_scored += record.scored
            self.counts.rerank_budget_cut += int(0 < record.scored < record.candidates)
        return record

    def _stored_features(self, kf_id: int) -> Features | None:
        return self.geometry.unpack(self._place_map.features(kf_id))

    def _scale_neighbours(self, match_id: int) -> list[Neighbour]:
        """Map keyframes next to the match (by id: recorded just before or after it) with an
        odometry baseline, for the scale of a monocular loop."""
        span = self.geometry.config.pose.scale_neighbours
        ids = [i for i in range(match_id - span, match_id + span + 1)
               if i != match_id and 0 <= i < len(self._place_map)]  # fmt: skip
        near = [self._place_map.meta(i) for i in ids]
        meta = self._place_map.meta(match_id)
        return self.geometry.neighbours(meta, near, self._stored_features)

    def _candidate(self, kf_id: int, sim: float, rank: int) -> Candidate:
        meta = self._place_map.meta(kf_id)
        return Candidate(kf_id, meta.stamp, meta.frame_id, float(sim), rank)

    def pair_scores(self, dense: np.ndarray, ids: list[int]) -> np.ndarray:
        """Query dense [N,D] against map keyframes `ids` -> bidirectional scores [K]."""
        return map_pair_scores(self.model, self._place_map, dense, ids, self.rerank_chunk)


def frame_due(stamp: float, last: float | None, interval: float) -> bool:
    """The frame-rate limit: is a frame at `stamp` (s) at least `interval` s from the last one
    let through, at `last` (None: none yet)? The pipeline asks it before encoding; the node
    asks it before queueing, so frames the pipeline would skip never wait in its queue."""
    return last is None or abs(stamp - last) >= interval


def encode_for_map(model: PairVPRModel, images: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Preprocessed images [B,3,S,S] -> what the map stores: dense tokens float16 [B,N,D] and
    descriptors float32 [B,desc_dim]. Queries are rounded to float16 too, so a query scores
    exactly like the same image stored in the map."""
    with torch.inference_mode():
        dense, desc = model.encode(images.to(model.device, non_blocking=True))
    return dense.to(torch.float16).cpu().numpy(), desc.float().cpu().numpy()


def map_pair_scores(
    model: PairVPRModel,
    place_map: PlaceMap,
    dense: np.ndarray,
    ids: list[int],
    chunk: int | None = None,
) -> np.ndarray:
    """Query dense [N,D] against the dense tokens of map keyframes ``ids`` -> bidirectional
    pair scores float32 [K] (the node's re-ranking, and ``pairvpr-eval``'s)."""
    device, dtype = model.device, model.dense_dtype
    q = torch.from_numpy(np.asarray(dense)).to(device=device, dtype=dtype)
    c = torch.from_numpy(place_map.get_dense(ids)).to(device=device, dtype=dtype)
    with torch.inference_mode():
        return model.pair_scores(q, c, chunk=chunk).float().cpu().numpy()
