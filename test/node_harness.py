"""`vpr_node` in-process for the tests of test/ros: the node under test (tiny random network,
settings under which only exact repeats of images are loops) and a peer node that publishes its
inputs, listens to every output and calls its services; both spin in one executor thread.
Everything waits on conditions, never on time alone (2 busy cores)."""

from __future__ import annotations

import threading
from collections import defaultdict

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from exact_match import EXACT_MATCH
from nav_msgs.msg import Odometry
from rclpy.executors import MultiThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile
from ros_cli import wait_for
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, String
from visualization_msgs.msg import MarkerArray

from pair_vpr_ros.ros.node import VprNode

EXACT = dict(
    weights="random-tiny",
    **EXACT_MATCH,
    min_frame_interval=0.0,
    qos="reliable",
    queue_size=50,
    diagnostics_period=0.2,
)
OUTPUTS = {
    "loop_closure": Float64MultiArray,
    "loop_closure/detail": Float64MultiArray,
    "loop_closure/json": String,
    "loop_closure/markers": MarkerArray,
    "loop_closure/factor": Odometry,
    "loop_closure/image": Image,
    "/diagnostics": DiagnosticArray,
}


class Harness:
    """The node under test and a peer that publishes, listens and calls services."""

    def __init__(self, start_worker: bool = True, remap: str = "", **overrides) -> None:
        """`remap`: a new name for `loop_closure` (-r loop_closure:=REMAP); `got` keeps the
        messages under the default names either way."""
        values = {**EXACT, **overrides}
        args = ["--ros-args", "-r", f"loop_closure:={remap}"] if remap else None
        self.node = VprNode(
            parameter_overrides=[Parameter(k, value=v) for k, v in values.items()],
            start_worker=start_worker,
            cli_args=args,
        )
        self.peer = rclpy.create_node("peer")
        self.got: dict[str, list] = defaultdict(list)
        for topic, msg_type in OUTPUTS.items():
            name = topic.replace("loop_closure", remap, 1) if remap else topic
            self.peer.create_subscription(msg_type, name, self.got[topic].append, 50)
        self.pub = self.peer.create_publisher(Image, "image", QoSProfile(depth=50))
        self.executor = MultiThreadedExecutor(num_threads=4)
        for node in (self.node, self.peer):
            self.executor.add_node(node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()
        if self.node.rig is None:  # a rig's cameras have topics of their own (test_node_rig.py)
            wait_for(lambda: self.pub.get_subscription_count() >= 1)
        wait_for(lambda: self.node.pub_pair.get_subscription_count() >= 1)

    def publish(self, images, t0: float = 100.0, frame_id: str = "cam") -> None:
        for i, rgb in enumerate(images):
            self.pub.publish(image_msg(rgb, t0 + i, frame_id))

    def processed(self, n: int) -> None:
        wait_for(lambda: self.node.stats.counts.processed >= n)

    def call(self, srv_type, name: str, **fields):
        client = self.peer.create_client(srv_type, f"/vpr_node/{name}")
        assert client.wait_for_service(timeout_sec=10.0)
        future = client.call_async(srv_type.Request(**fields))
        wait_for(future.done)
        return future.result()

    def set(self, **values):
        return self.node.set_parameters([Parameter(k, value=v) for k, v in values.items()])

    def close(self) -> None:
        if self.executor is None:
            return
        self.executor.shutdown()
        self.executor = None
        self.thread.join(5.0)
        self.node.shutdown()
        self.node.destroy_node()
        self.peer.destroy_node()


def stamp_msg(msg, t: float, frame_id: str = "cam"):
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(round(t * 1e9), 10**9)
    msg.header.frame_id = frame_id
    return msg


def image_msg(rgb: np.ndarray, t: float, frame_id: str = "cam", encoding: str = "rgb8", data=None):
    h, w = rgb.shape[:2]
    data = rgb.tobytes() if data is None else data
    msg = Image(height=h, width=w, encoding=encoding, step=len(data) // h, data=data)
    return stamp_msg(msg, t, frame_id)


def diagnostics(h: Harness) -> dict[str, str]:
    """The values of the newest /diagnostics message ({} before the first)."""
    if not h.got["/diagnostics"]:
        return {}
    return {kv.key: kv.value for kv in h.got["/diagnostics"][-1].status[0].values}
