"""The demo robot's rear camera and a lap driven the other way round (issue 49): the front
camera's frames stay as they were, the rear camera on the reversed lap looks where the front
camera looked on lap 0, its extrinsic agrees with the renderer, and a rig bag holds both
cameras and /tf_static."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_demo_world import read_bag

from pair_vpr_ros.demo import generate_world, render_frame, rig_summary
from pair_vpr_ros.demo.bag import write_world_bag
from pair_vpr_ros.demo.camera import Camera, to_camera
from pair_vpr_ros.demo.rig import (
    REAR_IMAGE_TOPIC,
    rear_pose,
    rear_to_base,
    render_rear,
)
from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry.rotations import quaternion_matrix

SIZE = dict(width=64, height=48)


def test_a_reversed_lap_leaves_the_other_laps_and_the_front_frames_as_they_were():
    plain = generate_world(3, frames=60, **SIZE)
    rig = generate_world(3, frames=60, reverse_laps=(1,), **SIZE)
    first, back = np.flatnonzero(plain.lap == 0), np.flatnonzero(plain.lap == 1)
    np.testing.assert_array_equal(rig.poses[first], plain.poses[first])
    assert np.array_equal(render_frame(rig, 5), render_frame(plain, 5))
    near = [first[np.argmin(np.hypot(*(rig.poses[first, :2] - rig.poses[j, :2]).T))]
            for j in back]  # fmt: skip
    turn = np.abs(np.angle(np.exp(1j * (rig.poses[back, 2] - rig.poses[near, 2]))))
    assert np.mean(turn > math.radians(150)) > 0.9  # driven the other way round


def test_on_the_reversed_lap_the_rear_camera_looks_where_the_front_camera_looked():
    world = generate_world(7, frames=600, reverse_laps=(1,), **SIZE)
    for i in (20, 60, 120):  # lap 0
        later = np.flatnonzero(world.lap == 1)
        j = later[np.argmin(np.hypot(*(world.poses[later, :2] - world.poses[i, :2]).T))]
        rear = rear_pose(world.poses[j])
        assert abs(math.remainder(rear[2] - world.poses[i, 2], math.tau)) < math.radians(30)
        assert np.hypot(*(rear[:2] - world.poses[i, :2])) < 8.0
    assert render_rear(world, 3).shape == (48, 64, 3)


def test_rear_to_base_maps_base_points_like_the_renderer():
    cam = Camera()
    pose7 = rear_to_base(cam)
    base = np.array([3.0, -2.0, 0.7])  # x, y, yaw of base_link
    c, s = math.cos(base[2]), math.sin(base[2])
    rot_wb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    point = np.array([-10.0, 4.0, 2.5])
    in_base = rot_wb.T @ (point - [base[0], base[1], 0.0])
    in_camera = quaternion_matrix(pose7[3:]).T @ (in_base - pose7[:3])
    np.testing.assert_allclose(in_camera, to_camera(point, rear_pose(base), cam), atol=1e-12)


def test_a_rig_bag_holds_both_cameras_and_their_poses(tmp_path):
    world = generate_world(3, frames=24, reverse_laps=(1,), **SIZE)
    conns, msgs = read_bag(write_world_bag(world, tmp_path / "rig.mcap", rear=True))
    assert conns[REAR_IMAGE_TOPIC] == ("sensor_msgs/msg/Image", 24)
    assert conns["/rear_camera/depth/image_raw"][1] == conns["/camera/image_raw"][1] == 24
    assert {m.header.frame_id for _, m in msgs[REAR_IMAGE_TOPIC]} == {"rear_camera"}
    ((_, tf),) = msgs["/tf_static"]
    got = {t.child_frame_id: t.transform.translation.x for t in tf.transforms}
    assert got == {"camera": 0.0, "rear_camera": -1.0}
    rear = msgs[REAR_IMAGE_TOPIC][4][1]
    np.testing.assert_array_equal(np.asarray(rear.data).reshape(48, 64, 3), render_rear(world, 4))


@pytest.mark.parametrize("laps", [(0,), (3,), ("1",)])
def test_a_reversed_lap_that_is_no_later_lap_is_refused(laps):
    with pytest.raises(ConfigError, match=r"reverse_laps=.*: each a lap in 1\.\.2"):
        generate_world(3, frames=60, reverse_laps=laps)


def _run(folder, name, opposite, precision, ate):
    (folder / name).mkdir(parents=True)
    (folder / f"{name}_posegraph").mkdir()
    summary = {"evaluation": {"precision": precision, "recall": 0.9}, "loops": 7,
               "directions": {"opposite": {"recall": opposite, "positives": 50},
                              "same": {"recall": 0.99}},
               "pipeline_counts": {"pose_metric": 5}}  # fmt: skip
    (folder / name / "summary.json").write_text(json.dumps(summary))
    errors = {"optimised": {"ate_rmse": ate}, "odometry": {"ate_rmse": 3.0}}
    (folder / f"{name}_posegraph" / "posegraph.json").write_text(json.dumps({"errors": errors}))


def test_the_rig_summary_puts_both_runs_and_the_targets_side_by_side(tmp_path, capsys):
    _run(tmp_path, "front_only", 0.1, 0.99, 0.3)
    _run(tmp_path, "rig", 0.9, 0.97, 0.2)
    assert rig_summary.main([str(tmp_path)]) == 0
    out = json.loads((tmp_path / "rig_summary.json").read_text())
    assert (out["front_only"]["opposite_recall"], out["rig"]["ate_m"]) == (0.1, 0.2)
    assert out["targets"] == {"rig opposite_recall >= 0.8": True, "rig precision >= 0.98": False,
                              "rig ate_m <= front_only ate_m": True}  # fmt: skip
    assert "rig precision >= 0.98: NOT met" in capsys.readouterr().out
    assert rig_summary.main([str(tmp_path / "nothing")]) == 2  # not run yet: says so
