"""ROS-free pieces of `vpr_node`: model loading, precision, the frame queue, poses, statistics.

Kept apart from `node.py` so they are tested without rclpy; the node only wires them to topics.
"""

from __future__ import annotations

import bisect
import contextlib
import threading
from collections import Counter, deque
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from .devices import check_device
from .errors import CheckpointError, ConfigError
from .model import ModelConfig, build_pairvpr, load_pairvpr, quantize_int8
from .node_params import RANDOM_TINY

WEIGHTS_HINT = "pass --ros-args -p weights:=/path/pairvpr-vitB.pth"


def load_model(weights: str, device: str = "cpu", precision: str = "fp32", image_size: int = 0):
    """The network the node runs -> `PairVPR` on `device` (int8: a quantized CPU copy).

    `weights` is a checkpoint path or `RANDOM_TINY`; `image_size` 0 keeps the checkpoint's.
    Raises `CheckpointError` (missing / unreadable weights) or `ConfigError` (device, precision).
    """
    if not weights:
        raise CheckpointError(f"no weights given: {WEIGHTS_HINT} (a Pair-VPR checkpoint)")
    check_device(device)
    kind = torch.device(device).type
    if precision == "int8" and kind != "cpu":
        raise ConfigError("precision int8 runs on the CPU only: use device:=cpu or bf16/fp16")
    if precision == "fp16" and kind != "cuda":
        raise ConfigError("precision fp16 needs a CUDA device: use device:=cuda, or bf16 on CPU")
    if weights == RANDOM_TINY:
        cfg = ModelConfig.tiny(**({"image_size": image_size} if image_size else {}))
        model = build_pairvpr(cfg, device=device, seed=0)
    else:
        try:
            model = load_pairvpr(weights, device=device, image_size=image_size or None)
        except CheckpointError as err:
            raise CheckpointError(f"{err}; {WEIGHTS_HINT}") from err
    return quantize_int8(model) if precision == "int8" else model


def precision_context(device: str, precision: str) -> contextlib.AbstractContextManager:
    """Autocast for bf16 / fp16 (thread-local: enter it in the thread that runs the model)."""
    if precision not in ("bf16", "fp16"):
        return contextlib.nullcontext()
    dtype = torch.bfloat16 if precision == "bf16" else torch.float16
    return torch.autocast(device_type=torch.device(device).type, dtype=dtype)


class FrameQueue:
    """Bounded FIFO between the image callback and the worker; a full queue drops its oldest."""

    def __init__(self, size: int) -> None:
        self._items: deque[Any] = deque(maxlen=size)
        self._cond = threading.Condition()
        self._closed = False
        self.dropped = 0

    def put(self, item: Any) -> bool:
        """Enqueue `item`; True when the oldest waiting item was dropped to make room."""
        with self._cond:
            full = len(self._items) == self._items.maxlen
            self._items.append(item)
            self.dropped += full
            self._cond.notify()
            return full

    def get(self, timeout: float) -> Any | None:
        """The oldest item, or None after `timeout` s or once closed."""
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items and not self._closed else None

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def snapshot(self) -> list[Any]:
        with self._cond:
            return list(self._items)

    def __len__(self) -> int:
        return len(self._items)


class PoseBuffer:
    """The newest `size` poses by stamp; `nearest` attaches one to a frame."""

    def __init__(self, size: int) -> None:
        self._size = size
        self._stamps: list[float] = []
        self._poses: list[tuple[float, ...]] = []
        self._lock = threading.Lock()

    def add(self, stamp: float, pose: tuple[float, ...]) -> None:
        """Insert a pose (x, y, z, qx, qy, qz, qw) at `stamp` s; out-of-order stamps are fine."""
        with self._lock:
            i = bisect.bisect_right(self._stamps, stamp)
            self._stamps.insert(i, stamp)
            self._poses.insert(i, pose)
            if len(self._stamps) > self._size:
                del self._stamps[0], self._poses[0]

    def nearest(self, stamp: float, tolerance: float) -> tuple[float, ...] | None:
        """The pose closest in time to `stamp`, or None when none is within `tolerance` s."""
        with self._lock:
            i = bisect.bisect_left(self._stamps, stamp)
            near = [j for j in (i - 1, i) if 0 <= j < len(self._stamps)]
            if not near:
                return None
            best = min(near, key=lambda j: abs(self._stamps[j] - stamp))
            return self._poses[best] if abs(self._stamps[best] - stamp) <= tolerance else None

    def __len__(self) -> int:
        return len(self._stamps)


class NodeStats:
    """Counters and recent latencies (ms) of the node, summarised for `/diagnostics`.

    Writers: the image callback (`received`, `invalid`, `dropped`), the worker (`processed`,
    `errors`, timings). Latency windows hold the last `window` values.
    """

    def __init__(self, window: int = 300) -> None:
        self.counts: Counter[str] = Counter()
        self._window = window
        self._ms: dict[str, deque[float]] = {}
        self._lock = threading.Lock()
        self._last: Counter[str] = Counter()

    def add_ms(self, key: str, ms: float) -> None:
        with self._lock:
            self._ms.setdefault(key, deque(maxlen=self._window)).append(ms)

    def percentiles(self, key: str) -> tuple[float, float, float] | None:
        """(p50, p95, max) of the recent `key` latencies, None before the first one."""
        with self._lock:
            values = np.array(self._ms.get(key, ()), dtype=np.float64)
        if not len(values):
            return None
        p50, p95 = np.percentile(values, [50, 95])
        return float(p50), float(p95), float(values.max())

    def increases(self, *keys: str) -> dict[str, int]:
        """How much each counter grew since the previous call (for warning levels)."""
        out = {k: self.counts[k] - self._last[k] for k in keys}
        for k in keys:
            self._last[k] = self.counts[k]
        return out

    def problems(self) -> str:
        """What went wrong since the previous call, e.g. "3 frames dropped" ("" when nothing)."""
        grew = self.increases("dropped", "invalid", "errors")
        words = {"dropped": "dropped", "invalid": "invalid", "errors": "failed"}
        return ", ".join(f"{n} frames {words[key]}" for key, n in grew.items() if n)

    def latency_items(self) -> Iterator[tuple[str, str]]:
        """("<key>_ms_p50" / "_p95" / "_max", value) for every latency window."""
        with self._lock:
            keys = sorted(self._ms)
        for key in keys:
            stats = self.percentiles(key)
            if stats is not None:
                for label, value in zip(("p50", "p95", "max"), stats, strict=True):
                    yield f"{key}_ms_{label}", f"{value:.2f}"


def bytes_per_keyframe(place_map: Any) -> int:
    """Stored bytes of one keyframe: float16 dense tokens + float32 descriptor (metadata aside)."""
    n, d = place_map.dense_shape
    return 2 * n * d + 4 * place_map.desc_dim


def diagnostic_values(
    values: dict, pipeline: Any, stats: NodeStats, frames: FrameQueue, maps: Any
):
    """The `/diagnostics` key/values of the node: settings, counters, map size, latencies.

    `values`: the node's parameters; `maps`: its `MapControl` (size, build_state)."""
    c, size = stats.counts, maps.size()
    per_kf = bytes_per_keyframe(pipeline.place_map)
    out = {
        "mode": pipeline.config.mode,
        "device": values["device"],
        "precision": values["precision"],
        "queue_depth": len(frames),
        "queue_size": values["queue_size"],
        "frames_received": c["received"],
        "frames_processed": c["processed"],
        "frames_dropped": c["dropped"],
        "frames_invalid": c["invalid"],
        "frames_rate_limited": pipeline.counts["rate_limited"],
        "frames_similar_to_keyframe": pipeline.counts["similar_to_keyframe"],
        "frames_failed": c["errors"],
        "loops": c["loops"],
        "map_size": size,
        "bytes_per_keyframe": per_kf,
        "map_bytes": size * per_kf,
        "map_dir": values["map_dir"],
        "build": maps.build_state,
    }
    return {**{k: str(x) for k, x in out.items()}, **dict(stats.latency_items())}
