"""`LoopClosurePipeline`: the one object that turns camera frames into loop-closure records.

The ROS node (`node.py`) feeds it frame by frame from a worker thread; the bag replay feeds it
batches (`process_many`). Both give the same records for the same frames: frame-rate limiting
depends only on stamps, so batching the encoder changes nothing but speed.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .detector import Candidate, DetectorConfig, LoopDetector, LoopRecord
from .errors import ConfigError, MapFingerprintError
from .geometry import Features, extract_features, verify_pair
from .model import PairVPR, preprocess_batch
from .place_map import KeyframeMeta, PlaceMap


@dataclass
class Frame:
    """One camera frame: RGB uint8 [H,W,3], header stamp in seconds, optional pose
    (x, y, z, qx, qy, qz, qw)."""

    stamp: float
    rgb: np.ndarray
    frame_id: str = ""
    pose: tuple[float, ...] | None = None
    source: str = ""


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


class LoopClosurePipeline:
    """Frames -> encoder -> keyframe selection -> map query -> pair re-ranking -> LoopRecords.

    Thread-safe: the node's worker thread processes frames while service callbacks save, load,
    clear or switch mode.
    """

    def __init__(
        self,
        model: PairVPR,
        config: DetectorConfig | None = None,
        place_map: PlaceMap | None = None,
        index: str = "flat",
        rerank_chunk: int | None = None,
    ) -> None:
        self.model = model.eval()
        self.detector = LoopDetector(config or DetectorConfig())
        self.index_kind = index
        self.rerank_chunk = rerank_chunk
        self._lock = threading.RLock()
        self._place_map = place_map if place_map is not None else self._new_map()
        self._check_fingerprint(self._place_map)
        # ORB features for geometric verification, for keyframes added in this process only.
        self._features: dict[int, Features] = {}
        self._stamps: list[float] = []  # keyframe stamps by id, for recent-frame exclusion
        self._last_encoded: float | None = None
        self._last_desc: np.ndarray | None = None
        self._reset_tracking()
        self.counts: Counter[str] = Counter()
        self.timing_totals: Counter[str] = Counter()

    # ---- state -----------------------------------------------------------------------------
    @property
    def config(self) -> DetectorConfig:
        return self.detector.config

    @property
    def place_map(self) -> PlaceMap:
        return self._place_map

    def set_config(self, config: DetectorConfig) -> None:
        with self._lock:
            self.detector.set_config(config)

    def set_mode(self, mode: str) -> None:
        """ "mapping" (query, then add each keyframe) or "localization" (query only)."""
        self.set_config(self.config.updated(mode=mode))

    def _new_map(self) -> PlaceMap:
        cfg = self.model.config
        return PlaceMap(
            desc_dim=cfg.desc_dim,
            dense_shape=(self.model.num_patches, cfg.embed_dim),
            fingerprint=self.model.fingerprint,
            index=self.index_kind,
        )

    def _check_fingerprint(self, place_map: PlaceMap) -> None:
        if place_map.fingerprint != self.model.fingerprint:
            raise MapFingerprintError(
                f"the map was built with model {place_map.fingerprint!r} but this pipeline runs "
                f"{self.model.fingerprint!r}: use the same weights and image size, or rebuild it"
            )

    def _reset_tracking(self) -> None:
        self._stamps = [m.stamp for m in self._place_map.all_meta()]
        self._features.clear()
        self._last_encoded = None
        self._last_desc = None
        self.detector.reset()

    def save_map(self, directory: str | Path) -> Path:
        with self._lock:
            return self._place_map.save(directory)

    def load_map(self, directory: str | Path) -> int:
        """Replace the map by a saved one (same model required); returns its keyframe count.

        Reloading the folder the current map was saved to discards its unsaved keyframes (the
        folder is locked by the current map, so that one is closed first)."""
        with self._lock:
            current = self._place_map
            same = current.directory is not None and current.directory == Path(directory).resolve()
            if same:
                current.close()
            try:
                loaded = PlaceMap.load(directory, expected_fingerprint=self.model.fingerprint)
            except Exception:
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
        with self._lock:
            self._place_map.clear()
            self._reset_tracking()

    def close(self) -> None:
        self._place_map.close()

    # ---- processing ------------------------------------------------------------------------
    def due(self, stamp: float) -> bool:
        """Frame-rate limit: is a frame at `stamp` far enough from the last encoded one?"""
        last = self._last_encoded
        return last is None or abs(stamp - last) >= self.config.min_frame_interval

    def process(self, frame: Frame) -> FrameOutcome:
        """Run one frame through the whole pipeline."""
        return next(self.process_many([frame], batch_size=1))

    def process_many(self, frames: Iterable[Frame], batch_size: int = 8) -> Iterator[FrameOutcome]:
        """Frames in time order -> one outcome each; the encoder runs on batches of due frames."""
        if batch_size < 1:
            raise ConfigError(f"batch size must be >= 1, got {batch_size}")
        batch: list[Frame] = []
        for frame in frames:
            with self._lock:
                if not self.due(frame.stamp):
                    self.counts["rate_limited"] += 1
                    yield FrameOutcome(frame.stamp, skipped="rate limited")
                    continue
                self._last_encoded = frame.stamp
            batch.append(frame)
            if len(batch) >= batch_size:
                yield from self._run_batch(batch)
                batch = []
        if batch:
            yield from self._run_batch(batch)

    def encode(self, images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """RGB uint8 images -> dense float16 [B,N,D], descriptors float32 [B,desc_dim]."""
        x = preprocess_batch(images, self.model.config.image_size).to(self.model.device)
        with torch.inference_mode():
            dense, desc = self.model.encode(x)
        return dense.to(torch.float16).cpu().numpy(), desc.float().cpu().numpy()

    def _run_batch(self, batch: list[Frame]) -> Iterator[FrameOutcome]:
        t0 = time.perf_counter()
        dense, desc = self.encode([f.rgb for f in batch])
        encode_ms = (time.perf_counter() - t0) * 1e3 / len(batch)
        for i, frame in enumerate(batch):
            with self._lock:
                outcome = self._decide(frame, dense[i], desc[i])
            outcome.timings_ms["encode"] = encode_ms
            self.counts["encoded"] += 1
            for key, ms in outcome.timings_ms.items():
                self.timing_totals[key] += ms
            yield outcome

    def _decide(self, frame: Frame, dense: np.ndarray, desc: np.ndarray) -> FrameOutcome:
        outcome = FrameOutcome(frame.stamp)
        last = self._last_desc
        if not self.detector.is_new_keyframe(None if last is None else float(desc @ last)):
            self.counts["similar_to_keyframe"] += 1
            outcome.skipped = "similar to previous keyframe"
            return outcome
        features = extract_features(frame.rgb) if self.config.geometric_verification else None
        outcome.loop = self._query(frame, dense, desc, outcome, features)
        if self.config.mode == "mapping":
            meta = KeyframeMeta(
                stamp=frame.stamp, frame_id=frame.frame_id, pose=frame.pose, source=frame.source
            )
            outcome.keyframe_id = self._place_map.add(desc, dense, meta)
            self._stamps.append(frame.stamp)
            if features is not None:
                self._features[outcome.keyframe_id] = features
            if outcome.loop is not None:
                outcome.loop.query_id = outcome.keyframe_id
        self._last_desc = desc
        self.counts["keyframes"] += 1
        if outcome.loop is not None:
            self.counts["loops" if outcome.loop.accepted else "rejected"] += 1
        return outcome

    def _query(self, frame: Frame, dense, desc, outcome: FrameOutcome, features: Features | None):
        max_id = self.detector.eligible_max_id(frame.stamp, self._stamps)
        if max_id is None:
            return None
        timings = outcome.timings_ms
        t0 = time.perf_counter()
        hits = self._place_map.search(desc, self.config.top_k, max_id=max_id)
        timings["search"] = (time.perf_counter() - t0) * 1e3
        outcome.candidates = candidates = [
            self._candidate(kf_id, sim, rank) for rank, (kf_id, sim) in enumerate(hits, start=1)
        ]

        def rerank(cands: list[Candidate]) -> np.ndarray:
            t1 = time.perf_counter()
            scores = self.pair_scores(dense, [c.id for c in cands])
            timings["rerank"] = (time.perf_counter() - t1) * 1e3
            return scores

        def verify(match_id: int) -> tuple[int, float]:
            stored = self._features.get(match_id)
            if features is None or stored is None:
                return -1, float("nan")  # keyframe loaded from disk: nothing to verify against
            return verify_pair(features, stored)

        return self.detector.decide(frame.stamp, frame.frame_id, candidates, rerank, verify)

    def _candidate(self, kf_id: int, sim: float, rank: int) -> Candidate:
        meta = self._place_map.meta(kf_id)
        return Candidate(kf_id, meta.stamp, meta.frame_id, float(sim), rank)

    def pair_scores(self, dense: np.ndarray, ids: list[int]) -> np.ndarray:
        """Query dense [N,D] against map keyframes `ids` -> bidirectional scores [K]."""
        device = self.model.device
        dtype = self.model.decoder_embed.weight.dtype
        q = torch.from_numpy(np.asarray(dense)).to(device=device, dtype=dtype)
        c = torch.from_numpy(self._place_map.get_dense(ids)).to(device=device, dtype=dtype)
        with torch.inference_mode():
            return self.model.pair_scores(q, c, chunk=self.rerank_chunk).float().cpu().numpy()
