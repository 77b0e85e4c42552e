"""The node's geometry inputs without ROS: stereo right images and baseline, a camera_info
topic that stays silent (said once), bad right camera_info counted, the depth wait
(depth_max_delay) with late depth images counted apart from missing ones."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import numpy as np
from bag_fixtures import TS2, image_msg, textured

from pair_vpr_ros.params.configs import defaults
from pair_vpr_ros.ros.geometry_inputs import GeometryInputs


def inputs(**values):
    counts = SimpleNamespace(
        camera_info_invalid=0, depth_unmatched=0, depth_invalid=0, depth_late=0
    )
    return GeometryInputs({**defaults(), "depth_max_delay": 0.0, **values}, counts), counts


def depth_msg(stamp: float) -> SimpleNamespace:
    """A 4x2 32FC1 depth image of 2 m stamped `stamp` (duck-typed like rclpy's)."""
    data = np.full((2, 4), 2.0, np.float32).tobytes()
    sec, nsec = divmod(round(stamp * 1e9), 10**9)
    header = SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nsec))
    return SimpleNamespace(header=header, encoding="32FC1", height=2, width=4, step=16,
                           is_bigendian=0, data=data)  # fmt: skip


def test_depth_max_delay_is_the_wait_and_late_depth_is_counted_apart():
    g, counts = inputs(depth_topic="/depth", depth_max_delay=0.0)
    assert g.wait == 0.0 and defaults()["depth_max_delay"] == 0.2
    assert g.depth_for(5.0) is None
    assert counts.depth_unmatched == 1 and counts.depth_late == 0
    assert g.last_problem == (
        "no depth image stamped within depth_tolerance 0.02 s of the image (5.000) arrived "
        "within depth_max_delay 0.0 s (diagnostics depth_late counts the ones that came later)"
    )
    g.on_depth(depth_msg(5.01))  # came after the frame gave up: late, not missing
    g.on_depth(depth_msg(9.0))  # no frame waited for this one
    assert counts.depth_late == 1
    assert g.depth_for(6.0) is None and counts.depth_unmatched == 2 and counts.depth_late == 1
    np.testing.assert_array_equal(g.depth_for(9.0), np.full((2, 4), 2.0, np.float32))


def test_a_depth_image_within_the_wait_is_used():
    g, counts = inputs(depth_topic="/depth", depth_max_delay=5.0)
    threading.Timer(0.1, g.on_depth, (depth_msg(7.0),)).start()
    start = time.monotonic()
    depth = g.depth_for(7.0)
    assert depth is not None and time.monotonic() - start < 4.0
    assert counts.depth_unmatched == counts.depth_late == 0


def test_right_image_and_baseline_for_a_frame():
    g, counts = inputs(right_image_topic="/right")
    rgb = textured(2)
    g.on_right(image_msg(TS2, 3.0, rgb, compressed=False))
    assert g.on_right_camera_info(SimpleNamespace(p=[100.0, 0, 80, -25.0] + [0.0] * 8)) is None
    np.testing.assert_array_equal(g.right_for(3.01), rgb)
    assert g.right_for(3.5) is None  # beyond depth_tolerance
    assert g.baseline == 0.25
    problem = g.on_right_camera_info(SimpleNamespace(p=[100.0] + [0.0] * 11))
    assert problem.startswith("right camera_info: P[0, 3] = 0 gives no positive baseline")
    assert counts.camera_info_invalid == 1 and g.baseline == 0.25  # the good one stays


def test_no_right_topic_no_right_image():
    g, _ = inputs()
    g.on_right(image_msg(TS2, 3.0, textured(2), compressed=False))
    assert g.right_for(3.0) is None


def test_silent_camera_info_is_said_once_after_the_wait():
    g, _ = inputs(camera_info_topic="/cam/info")
    assert g.silence_note(100.0) == ""  # the first frame starts the clock
    assert g.silence_note(104.0) == ""
    assert g.silence_note(105.5).startswith("camera_info_topic /cam/info: no valid CameraInfo "
                                            "within 6 s of the first frame")  # fmt: skip
    assert g.silence_note(200.0) == ""  # once
    quiet, _ = inputs()
    assert quiet.silence_note(0.0) == quiet.silence_note(100.0) == ""


def test_the_first_frame_waits_once_for_a_camera_info_just_behind_it():
    counts = SimpleNamespace(camera_info_invalid=0, depth_unmatched=0, depth_invalid=0)
    values = {**defaults(), "camera_info_topic": "/cam/info", "depth_max_delay": 5.0}
    g = GeometryInputs(values, counts)
    info = SimpleNamespace(
        width=320, height=240, k=[200.0, 0, 160, 0, 200.0, 120, 0, 0, 1], d=[],
        distortion_model="plumb_bob", p=[200.0, 0, 160, 0, 0, 200.0, 120, 0, 0, 0, 1, 0],
    )  # fmt: skip
    threading.Timer(0.05, g.on_camera_info, [info]).start()
    g.await_first_camera_info()  # returns once the CameraInfo is in, well before 5 s
    assert g.camera_for(320, 240) is not None
    silent, _ = inputs(camera_info_topic="/cam/info")
    silent.wait = 0.05
    silent.await_first_camera_info()
    assert silent._info_waited  # one wait in vain, then never again
