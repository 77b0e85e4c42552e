"""ROS-free pieces of `vpr_node`: precision and threads, the frame queue, statistics.

Kept apart from `node.py` so they are tested without rclpy; the node only wires them to topics.
"""

from __future__ import annotations

import contextlib
import threading
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from pair_vpr_ros.model.threads import limit_this_thread
from pair_vpr_ros.ros.maps import MapControl


def precision_context(
    device: str | torch.device, precision: str
) -> contextlib.AbstractContextManager:
    """Autocast for bf16 / fp16 (thread-local: enter it in the thread that runs the model),
    and that thread's OpenMP pools sized as the process's (`threads.limit_this_thread`)."""
    limit_this_thread()
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


@dataclass
class NodeCounts:
    """Frames the node saw, by what became of them (`/diagnostics` reports each)."""

    received: int = 0  # image callback
    invalid: int = 0  # image callback: not convertible to RGB
    rate_limited: int = 0  # image callback: within min_frame_interval of the last queued frame
    dropped: int = 0  # image callback: the full queue dropped its oldest frame
    processed: int = 0  # worker: through the pipeline
    errors: int = 0  # worker: the pipeline raised
    loops: int = 0  # worker: accepted loop closures published
    loops_unordered: int = 0  # worker: accepted, match not older: no pair message
    bad_poses: int = 0  # pose callback: NaN / inf values, not stored
    camera_info_invalid: int = 0  # camera_info callback: unusable intrinsics (zero focal, ...)
    depth_unmatched: int = 0  # worker: no depth image within depth_tolerance of the frame
    # (arrived within depth_max_delay)
    depth_late: int = 0  # depth callback: the depth image of a frame that went on without it
    depth_invalid: int = 0  # worker: the matched depth image could not be read


class NodeStats:
    """Counters and recent latencies (ms) of the node, summarised for `/diagnostics`.

    Each counter has one writer (see `NodeCounts`). Latency windows hold the last `window`
    values.
    """

    def __init__(self, window: int = 300) -> None:
        self.counts = NodeCounts()
        self._window = window
        self._ms: dict[str, deque[float]] = {}
        self._lock = threading.Lock()
        self._reported = NodeCounts()  # at the previous `problems()`

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

    def problems(self) -> str:
        """What went wrong since the previous call, e.g. "3 frames dropped" ("" when nothing)."""
        now, last = replace(self.counts), self._reported
        self._reported = now
        grew = (
            (now.dropped - last.dropped, "frames dropped"),
            (now.invalid - last.invalid, "frames invalid"),
            (now.errors - last.errors, "frames failed"),
            (now.bad_poses - last.bad_poses, "poses invalid (NaN/inf)"),
            (now.camera_info_invalid - last.camera_info_invalid, "camera_info unusable"),
            (now.depth_unmatched - last.depth_unmatched, "frames without depth"),
            (now.depth_late - last.depth_late, "depth images too late (depth_max_delay)"),
            (now.depth_invalid - last.depth_invalid, "depth images invalid"),
        )
        return ", ".join(f"{n} {words}" for n, words in grew if n)

    def latency_items(self) -> Iterator[tuple[str, str]]:
        """("<key>_ms_p50" / "_p95" / "_max", value) for every latency window."""
        with self._lock:
            keys = sorted(self._ms)
        for key in keys:
            stats = self.percentiles(key)
            if stats is not None:
                for label, value in zip(("p50", "p95", "max"), stats, strict=True):
                    yield f"{key}_ms_{label}", f"{value:.2f}"


STAMP_AGE = (
    "stamp_age_ms_*: ROS time at processing minus the image header stamp; the ROS time is the "
    "wall clock unless use_sim_time is true, so a bag played without --clock and "
    "use_sim_time:=true reads its age since recording"
)


def diagnostic_values(
    values: dict, stats: NodeStats, frames: FrameQueue, maps: MapControl
) -> dict[str, str]:
    """The `/diagnostics` key/values of the node: settings, counters, map size, latencies.

    `values`: the node's parameters. The pipeline's part comes from `maps.state`, the copy its
    map thread made after its last task: this runs on the diagnostics timer's thread."""
    c, live = stats.counts, maps.state
    out = {
        "mode": live.mode,
        "device": values["device"],
        "precision": values["precision"],
        "queue_depth": len(frames),
        "queue_size": values["queue_size"],
        "frames_received": c.received,
        "frames_processed": c.processed,
        "frames_dropped": c.dropped,
        "frames_invalid": c.invalid,
        "frames_rate_limited": c.rate_limited + live.counts.rate_limited,
        "frames_rate_limited_unqueued": c.rate_limited,
        "frames_encoded": live.counts.encoded,
        "frames_similar_to_keyframe": live.counts.similar_to_keyframe,
        "frames_failed": c.errors,
        "poses_invalid": c.bad_poses,
        "loops": c.loops,
        "loops_unordered": c.loops_unordered,
        "clock_jumps": live.counts.clock_jumps,
        "loops_pose_metric": live.counts.pose_metric,
        "loops_pose_metric_odometry": live.counts.pose_metric_odometry,
        "loops_pose_scale_free": live.counts.pose_scale_free,
        "loops_pose_none": live.counts.pose_none,
        "candidates_scored": live.counts.candidates_scored,
        "decoder_passes": live.counts.decoder_passes,  # one direction of one pair each
        "rerank_budget_cut": live.counts.rerank_budget_cut,
        "rerank_skipped": live.counts.rerank_skipped,  # below global_floor / the learned floor
        "rerank_covered": live.counts.rerank_covered,  # every candidate scored one way at least
        "map_searches_skipped": live.counts.map_searches_skipped,  # index milvus unreachable
        "map_keyframes_pending": live.counts.map_keyframes_pending,
        "camera_info_invalid": c.camera_info_invalid,
        "frames_without_depth": c.depth_unmatched,
        # of these: the depth image came after depth_max_delay (late) or never (missing)
        "depth_late": c.depth_late,
        "depth_missing": max(0, c.depth_unmatched - c.depth_late),
        "depth_invalid": c.depth_invalid,
        "map_size": live.keyframes,
        "keyframes_represented": live.counts.represented,  # not stored: map_growth places
        "bytes_per_keyframe": live.bytes_per_keyframe,
        "map_bytes": live.keyframes * live.bytes_per_keyframe,
        "map_dir": values["map_dir"],
        "build": maps.build_state,
        "stamp_age": STAMP_AGE,
    }
    return {**{k: str(x) for k, x in out.items()}, **dict(stats.latency_items())}
