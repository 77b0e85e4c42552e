"""pairvpr-bag-replay with several cameras (issue 49): repeated --topic (extrinsics from the
bag's /tf_static) or a rig file; loops across cameras in the base frame in every output; bad
rigs refused before any frame is read, a silent camera and stamps apart counted (tiny random
model; revisits are exact repeats)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from bag_fixtures import TS2, _header, image_msg, textured, write_rosbag2
from test_replay_geometry import CONFIG, depth_msg, info_msg

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.offline.replay.cli import main
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag

FRONT = (0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5)
REAR = (-1.0, 0.0, 1.6, 0.5, 0.5, -0.5, -0.5)
PLACES = [textured(s) for s in range(8)]
STAMPS = [0.0, 1.0, 2.0, 4.0, 5.0]
# driven back: at t=5 the front camera sees what the rear one saw at t=0, and the other way
VIEWS = {"front": [0, 1, 2, 3, 5], "rear": [5, 6, 7, 4, 0]}
RIG_CONFIG = replace(CONFIG, map_growth="all")  # every keyframe stored (repeats are exact)


def _tf(frames: dict[str, tuple]):
    t = TS2.types
    out = [t["geometry_msgs/msg/TransformStamped"](
        header=_header(TS2, 0.0, "base_link"), child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
            rotation=t["geometry_msgs/msg/Quaternion"](x=p[3], y=p[4], z=p[5], w=p[6])),
    ) for child, p in frames.items()]  # fmt: skip
    return t["tf2_msgs/msg/TFMessage"](transforms=out)


def write_rig_bag(path, frame_ids=("front_cam", "rear_cam"), rear_until=99.0, rear_shift=0.0,
                  tf=True):  # fmt: skip
    """Both cameras' images, camera_info and depth (4 m) in their namespaces, /tf_static."""
    extra, mm = [], np.full((120, 160), 4000, np.uint16)
    for (name, views), frame in zip(VIEWS.items(), frame_ids, strict=True):
        shift = rear_shift if name == "rear" else 0.0
        for t, place in zip(STAMPS, views, strict=True):
            if name == "rear" and t > rear_until:
                continue
            msg = image_msg(TS2, t + shift, PLACES[place], False, frame_id=frame)
            extra += [(f"/{name}/image", "sensor_msgs/msg/Image", msg, t + shift),
                      (f"/{name}/depth", "sensor_msgs/msg/Image", depth_msg(t + shift, mm),
                       t + shift + 0.001)]  # fmt: skip
        extra.append((f"/{name}/camera_info", "sensor_msgs/msg/CameraInfo", info_msg(0.0), 0.0))
    if tf:
        poses = dict(zip(frame_ids, (FRONT, REAR), strict=True))
        extra.append(("/tf_static", "tf2_msgs/msg/TFMessage", _tf(poses), 0.0))
    return write_rosbag2(path, [], extra=extra)


def replay(tmp_path, bag, model, **kw):
    options = ReplayOptions(progress=False, overwrite=True, **kw)
    return replay_bag(bag, tmp_path / "out", options, model=model, config=RIG_CONFIG)


def _loops(tmp_path):
    records = json.loads((tmp_path / "out" / "loops.json").read_text())
    return [r for r in records if r["accepted"]]


def test_repeated_topics_make_a_rig_whose_loops_cross_cameras_in_the_base_frame(
    tmp_path, tiny_model
):
    bag = write_rig_bag(tmp_path / "bag")
    s = replay(tmp_path, bag, tiny_model, topics=("/front/image", "/rear/image"))
    assert s.notes[:3] == [
        "rig of 2 cameras from --topic /front/image --topic /rear/image: front (/front/image; "
        "camera_info /front/camera_info, depth /front/depth), rear (/rear/image; camera_info "
        "/rear/camera_info, depth /rear/depth); rig keyframes within 20 ms, loops in base_link",
        "rig camera front: camera_to_base from /tf_static (base_link -> front_cam)",
        "rig camera rear: camera_to_base from /tf_static (base_link -> rear_cam)",
    ]
    assert (s.frames, s.keyframes, s.loops) == (10, 10, 2)
    got = s.rig["cameras"][1]["camera_to_base"]  # from tf (q and -q: one rotation)
    assert got == pytest.approx([*REAR[:3], *(-v for v in REAR[3:])])
    assert (s.rig["keyframes"], s.rig["incomplete"]) == (5, 0)
    loops = _loops(tmp_path)
    assert [(r["query_camera"], r["match_camera"], r["match_stamp"]) for r in loops] == [
        (0, 1, 0.0), (1, 0, 0.0)]  # fmt: skip
    assert all(r["pose_status"] == "metric" and r["pose_frame"] == "base_link" for r in loops)
    # the same view from the front and the rear camera: T_base_rear T_front_base
    t = np.array([loops[0][k] for k in ("tx", "ty", "tz")])
    np.testing.assert_allclose(t, [-1.0, 0.0, 0.0], atol=0.02)


def test_a_rig_file_gives_the_same_loops(tmp_path, tiny_model):
    bag = write_rig_bag(tmp_path / "bag", tf=False)
    rig = tmp_path / "rig.yaml"
    rig.write_text(
        "cameras:\n"
        f"  - {{name: front, image_topic: /front/image, camera_info_topic: /front/camera_info,"
        f" depth_topic: /front/depth, camera_to_base: {list(FRONT)}}}\n"
        f"  - {{name: rear, image_topic: /rear/image, camera_info_topic: /rear/camera_info,"
        f" depth_topic: /rear/depth, camera_to_base: {list(REAR)}}}\n"
    )
    s = replay(tmp_path, bag, tiny_model, rig_file=rig)
    assert s.loops == 2 and s.topic == "/front/image, /rear/image"
    assert [(r["query_camera"], r["match_camera"]) for r in _loops(tmp_path)] == [(0, 1), (1, 0)]


def test_a_silent_camera_and_stamps_apart_are_counted_and_the_other_goes_on(tmp_path, tiny_model):
    bag = write_rig_bag(tmp_path / "bag", rear_until=1.5)
    s = replay(tmp_path, bag, tiny_model, topics=("/front/image", "/rear/image"))
    assert (s.frames, s.keyframes, s.rig["missing"]) == (7, 7, {"rear": 3})
    assert any("rig keyframes without a camera: rear (3) of 5" in w for w in s.warnings)
    bag = write_rig_bag(tmp_path / "bag2", rear_shift=0.3)
    s = replay(tmp_path, bag, tiny_model, topics=("/front/image", "/rear/image"))
    assert s.keyframes == 10 and s.rig["incomplete"] == 10  # every frame used, alone


@pytest.mark.parametrize(
    ("bag_kw", "message"),
    [
        (dict(tf=False), "rig camera 'front' has no extrinsic: its camera_to_base is not in the "
         "rig file and /tf_static of the bag has no transform from 'base_link' to its frame "
         "'front_cam'"),
        (dict(frame_ids=("cam", "cam")), "rig cameras 'front' and 'rear' have one frame id 'cam'"),
    ],
)  # fmt: skip
def test_a_rig_without_extrinsics_or_with_one_frame_id_is_refused(tmp_path, tiny_model, bag_kw,
                                                                   message):  # fmt: skip
    bag = write_rig_bag(tmp_path / "bag", **bag_kw)
    with pytest.raises(ConfigError, match=message):
        replay(tmp_path, bag, tiny_model, topics=("/front/image", "/rear/image"))
    assert not (tmp_path / "out" / "loops.json").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--rig", "r.yaml", "--topic", "/a"], "give --rig FILE or --topic, not both"),
        (["--topic", "/a", "--topic", "/b", "--depth-topic", "/d"],
         "--depth-topic with several cameras: give each camera's topics in a rig file"),
        (["--rig", "missing.yaml"], "rig file missing.yaml cannot be read"),
    ],
)  # fmt: skip
def test_rig_flags_that_do_not_go_together(tmp_path, capsys, argv, message):
    bag = write_rig_bag(tmp_path / "bag")
    code = main([str(bag), "--weights", str(tmp_path / "none.pth"), "--out",
                 str(tmp_path / "out"), *argv])  # fmt: skip
    assert code in (1, 2) and message in capsys.readouterr().err
