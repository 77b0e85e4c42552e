"""`pairvpr-bag-play` into a live graph: every message of the chosen topics arrives, in order,
as the type it was stored as, paced by --rate; --clock publishes the bag time."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import rclpy
from bag_fixtures import synthetic_images, write_rosbag2
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image

from pair_vpr_ros.ros.bag_play import message_class

ROOT = Path(__file__).resolve().parents[2]


def test_message_class_names_the_rclpy_type():
    assert message_class("sensor_msgs/msg/Image") is Image


@pytest.mark.slow  # a child process
def test_a_bag_plays_in_order_at_its_rate_with_the_clock(tmp_path):
    images = [(100.0 + 0.5 * i, rgb) for i, rgb in enumerate(synthetic_images(4, size=8))]
    poses = [(100.0 + 0.5 * i, (float(i), 0.0, 0.0)) for i in range(4)]
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    rclpy.init()
    node = rclpy.create_node("listener")
    got: dict[str, list] = {"image": [], "odom": [], "clock": []}
    deep = QoSProfile(depth=100)
    node.create_subscription(Image, "/cam/image", got["image"].append, deep)
    node.create_subscription(Odometry, "/odom", got["odom"].append, deep)
    node.create_subscription(Clock, "/clock", got["clock"].append, deep)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    thread = threading.Thread(target=executor.spin, daemon=True)
    thread.start()
    try:
        start = time.monotonic()
        done = subprocess.run(
            [sys.executable, "-m", "pair_vpr_ros.ros.bag_play", str(bag), "--rate", "2",
             "--clock", "--wait", "30"],
            cwd=ROOT, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        took = time.monotonic() - start
        assert done.returncode == 0, done.stderr
        assert "pairvpr-bag-play: 8 messages on 2 topics in " in done.stdout
        deadline = time.monotonic() + 10
        while len(got["image"]) < 4 and time.monotonic() < deadline:
            time.sleep(0.1)
        stamps = [m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for m in got["image"]]
        assert stamps == [100.0, 100.5, 101.0, 101.5]
        assert [m.pose.pose.position.x for m in got["odom"]] == [0.0, 1.0, 2.0, 3.0]
        assert got["image"][0].data.tobytes() == images[0][1].tobytes()
        assert len(got["clock"]) == 8 and got["clock"][-1].clock.sec == 101
        assert took >= 1.5 / 2  # 1.5 s of bag at rate 2
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        thread.join(5.0)
