"""A listener of a running vpr_node / posegraph_node pair (the live demo's eyes): every loop
record on `<loop_closure>/json`, the between-factors on `<loop_closure>/factor`, vpr_node's
`/diagnostics` counters and the newest `corrected_path`, spun on its own thread."""

from __future__ import annotations

import json
import threading
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry, Path
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String

DIAGNOSTICS_NAME = "vpr_node: loop closure"


class LoopRecorder:
    """Records what the two nodes publish; `close()` stops it. Its own rclpy context, so the
    caller's process may hold others."""

    def __init__(self, loop_closure: str = "loop_closure", path: str = "corrected_path") -> None:
        self.records: list[dict[str, Any]] = []
        self.factors = 0
        self.diagnostics: dict[str, str] = {}
        self.path: Path | None = None
        self._lock = threading.Lock()
        self._context = Context()
        # no signal handlers: Ctrl-C must reach the caller (demo.live stops the nodes then)
        rclpy.init(context=self._context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("pairvpr_loop_recorder", context=self._context)
        deep = QoSProfile(depth=1000)  # nothing lost while this thread is busy
        self.node.create_subscription(String, f"{loop_closure}/json", self._on_json, deep)
        self.node.create_subscription(Odometry, f"{loop_closure}/factor", self._on_factor, deep)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 10)
        self.node.create_subscription(Path, path, self._on_path, 1)
        self._executor = SingleThreadedExecutor(context=self._context)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()

    def _on_json(self, msg: String) -> None:
        with self._lock:
            self.records.append(json.loads(msg.data))

    def _on_factor(self, msg: Odometry) -> None:
        with self._lock:
            self.factors += 1

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == DIAGNOSTICS_NAME:
                with self._lock:
                    self.diagnostics = {kv.key: kv.value for kv in status.values}

    def _on_path(self, msg: Path) -> None:
        with self._lock:
            self.path = msg

    def counter(self, key: str) -> int:
        """One of vpr_node's `/diagnostics` counters (0 before the first message)."""
        with self._lock:
            return int(self.diagnostics.get(key, 0))

    def path_poses(self) -> tuple[list[float], list[list[float]]]:
        """The newest corrected path -> (stamps [K] s, poses [K][7] x y z qx qy qz qw)."""
        with self._lock:
            poses = list(self.path.poses) if self.path is not None else []
        stamps = [p.header.stamp.sec + p.header.stamp.nanosec * 1e-9 for p in poses]
        out = [[p.pose.position.x, p.pose.position.y, p.pose.position.z,
                p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z,
                p.pose.orientation.w] for p in poses]  # fmt: skip
        return stamps, out

    def close(self) -> None:
        self._executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self._context)
        self._thread.join(5.0)
