"""`vpr_node` with several cameras (issue 49): `cameras` and each camera's parameters, one map,
loops across cameras published in the base frame; a silent camera counted while the other goes
on; bad rigs refused at start-up (tiny random network, exact repeats as loops)."""

from __future__ import annotations

import json

import pytest
from bag_fixtures import textured
from nav_msgs.msg import Odometry
from node_harness import diagnostics, image_msg, wait_for
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from test_node_geometry import depth_msg, info_msg

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.messages.factor import FACTOR_TOPIC, factor_from_msg
from pair_vpr_ros.messages.loop import JSON_TOPIC

FRONT = [0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5]
REAR = [-1.0, 0.0, 1.6, 0.5, 0.5, -0.5, -0.5]
RIG = {
    "cameras": ["front", "rear"], "front.camera_to_base": FRONT, "rear.camera_to_base": REAR,
    "front.depth_topic": "front/depth", "rear.depth_topic": "rear/depth", "exclude_recent_s": 2.5,
    "map_growth": "all",
}  # fmt: skip
PLACES = [textured(s) for s in range(8)]
VIEWS = {"front": [0, 1, 2, 3, 5], "rear": [5, 6, 7, 4, 0]}  # driven back at t=104


def drive(h, rear_until: int = 5) -> tuple[list, list]:
    """Both cameras' camera_info, then their images and depth at t = 100..104."""
    peer, factors, records = h.peer, [], []
    peer.create_subscription(Odometry, FACTOR_TOPIC, factors.append, 10)
    peer.create_subscription(String, JSON_TOPIC, records.append, 10)
    pubs = {(name, kind): peer.create_publisher(msg_type, f"{name}/{kind}", 50)
            for name in VIEWS for kind, msg_type in (("image", Image), ("depth", Image),
                                                     ("camera_info", CameraInfo))}  # fmt: skip
    wait_for(lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()))
    for name in VIEWS:
        pubs[name, "camera_info"].publish(info_msg())
    wait_for(lambda: all(i.camera_info is not None for i in h.node.rig_inputs), 5.0)
    for t in range(5):
        for name, views in VIEWS.items():
            if name == "rear" and t >= rear_until:
                continue
            pubs[name, "depth"].publish(depth_msg(100.0 + t))
            pubs[name, "image"].publish(image_msg(PLACES[views[t]], 100.0 + t, f"{name}_cam"))
    return factors, records


def test_loops_cross_cameras_and_are_given_between_base_poses(harness):
    h = harness(**RIG)
    factors, records = drive(h)
    h.processed(10)
    wait_for(lambda: len(factors) == 2)
    got = sorted((f.query_camera, f.match_camera, f.query_frame_id) for f in map(factor_from_msg,
                 factors))  # fmt: skip
    assert got == [(0, 1, "base_link"), (1, 0, "base_link")]
    loops = [r for r in map(lambda m: json.loads(m.data), records) if r["accepted"]]
    assert {(r["query_frame_id"], r["match_frame_id"]) for r in loops} == {
        ("front_cam", "rear_cam"), ("rear_cam", "front_cam")}  # fmt: skip
    assert [m.camera for m in h.node.pipeline.place_map.all_meta()] == [0, 1] * 5
    wait_for(lambda: diagnostics(h).get("rig_keyframes") == "5")
    assert diagnostics(h)["rig_rear_missing"] == "0"
    assert "rig of front (front/image), rear (rear/image)" in h.node.summary


def test_a_camera_that_stops_publishing_is_counted_and_the_other_goes_on(harness):
    h = harness(**RIG)
    drive(h, rear_until=2)
    h.processed(7)
    wait_for(lambda: diagnostics(h).get("rig_rear_missing") == "3")
    assert diagnostics(h)["rig_incomplete"] == "3"


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ({"rear.camera_to_base": None}, "rig camera 'rear' has no extrinsic: give its "
         "camera_to_base"),
        ({"front.frame_id": "cam", "rear.frame_id": "cam"},
         "rig cameras 'front' and 'rear' have one frame id 'cam'"),
        ({"rear.camera_to_base": [0.0, 0.0, 1.0]}, "parameter rear.camera_to_base must be 7 "
         "finite numbers"),
    ],
)  # fmt: skip
def test_a_bad_rig_stops_the_node_at_start_with_what_to_do(harness, extra, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        values = {k: v for k, v in {**RIG, "rig_tf_wait": 0.0, **extra}.items() if v is not None}
        harness(**values)
