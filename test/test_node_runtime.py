"""ROS-free parts of the node: model loading, precision, frame queue, pose buffer, statistics."""

from __future__ import annotations

import threading

import pytest
import torch

from pair_vpr_ros.errors import CheckpointError, ConfigError
from pair_vpr_ros.node_runtime import (
    FrameQueue,
    NodeStats,
    PoseBuffer,
    bytes_per_keyframe,
    load_model,
    precision_context,
)
from pair_vpr_ros.place_map import PlaceMap


def test_missing_weights_say_what_to_pass(tmp_path):
    with pytest.raises(CheckpointError, match=r"^no weights given: pass --ros-args -p weights:="):
        load_model("")
    with pytest.raises(CheckpointError, match=r"does not exist.*-p weights:=/path/pairvpr-vitB"):
        load_model(str(tmp_path / "missing.pth"))
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="garbage.pth"):
        load_model(str(garbage))


@pytest.mark.parametrize(
    "device, precision, message",
    [
        ("gpu0", "fp32", "device 'gpu0' is not a torch device"),
        ("cpu", "fp16", "precision fp16 needs a CUDA device"),
        ("meta", "fp32", "only cpu and cuda devices are supported"),
    ],
)
def test_device_and_precision_are_checked(device, precision, message):
    with pytest.raises(ConfigError, match=message):
        load_model("random-tiny", device, precision)


def test_random_tiny_and_int8():
    model = load_model("random-tiny", image_size=28)
    assert model.config.image_size == 28 and model.fingerprint.startswith("random-init:0|tiny")
    assert load_model("random-tiny", precision="int8").fingerprint.startswith("random-init:0+int8")


def test_bf16_autocasts_in_the_thread_that_enters_it():
    seen = []

    def run():
        with precision_context("cpu", "bf16"):
            seen.append(torch.is_autocast_enabled("cpu") and torch.get_autocast_dtype("cpu"))

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    assert seen == [torch.bfloat16] and not torch.is_autocast_enabled("cpu")
    with precision_context("cpu", "fp32"):
        assert not torch.is_autocast_enabled("cpu")


def test_full_queue_drops_the_oldest():
    q = FrameQueue(2)
    assert [q.put(i) for i in range(5)] == [False, False, True, True, True]
    assert q.dropped == 3 and q.snapshot() == [3, 4] and len(q) == 2
    assert q.get(0.01) == 3 and q.get(0.01) == 4 and q.get(0.01) is None
    q.put(5)
    q.close()
    assert q.get(1.0) is None  # closed: the worker stops even with frames waiting


def test_pose_buffer_nearest_within_tolerance():
    buf = PoseBuffer(3)
    for stamp in (2.0, 0.0, 1.0, 3.0):  # out of order; capacity 3 keeps the newest stamps
        buf.add(stamp, (stamp, 0, 0, 0, 0, 0, 1))
    assert len(buf) == 3
    assert buf.nearest(1.4, 0.5)[0] == 1.0 and buf.nearest(2.6, 0.5)[0] == 3.0
    assert buf.nearest(0.0, 0.2) is None  # dropped by the capacity limit
    assert buf.nearest(4.0, 0.5) is None and PoseBuffer(3).nearest(1.0, 10.0) is None


def test_stats_percentiles_and_increases():
    stats = NodeStats(window=4)
    assert stats.percentiles("encode") is None
    for ms in (100.0, 1.0, 2.0, 3.0, 4.0):  # the window keeps the last 4
        stats.add_ms("encode", ms)
    assert stats.percentiles("encode") == (2.5, pytest.approx(3.85), 4.0)
    assert dict(stats.latency_items())["encode_ms_max"] == "4.00"
    stats.counts["dropped"] += 2
    assert stats.increases("dropped", "invalid") == {"dropped": 2, "invalid": 0}
    stats.counts["dropped"] += 1
    assert stats.increases("dropped") == {"dropped": 1}
    stats.counts["invalid"] += 2
    stats.counts["errors"] += 1
    assert stats.problems() == "2 frames invalid, 1 frames failed"
    assert stats.problems() == ""


def test_bytes_per_keyframe():
    with PlaceMap(desc_dim=512, dense_shape=(529, 768)) as m:
        assert bytes_per_keyframe(m) == 529 * 768 * 2 + 512 * 4
