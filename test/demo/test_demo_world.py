"""Synthetic loop world: determinism, trajectory ground truth, bag round trip, dataset, CLI."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from pair_vpr_ros.demo import generate_world, render_frame, write_demo_bag, write_place_dataset
from pair_vpr_ros.demo.camera import Camera, camera_to_base, to_camera
from pair_vpr_ros.demo.depth import depth_to_mm, render_depth
from pair_vpr_ros.demo.make_bag import main
from pair_vpr_ros.demo.odometry import OdometryNoise, drifting_odometry
from pair_vpr_ros.demo.world import LANE_OFFSET
from pair_vpr_ros.errors import BagError, ConfigError, DatasetError

FRAMES, SIZE = 60, (160, 120)


@pytest.fixture(scope="module")
def world():
    return generate_world(3, frames=FRAMES, width=SIZE[0], height=SIZE[1])


def read_bag(path: Path) -> tuple[dict, dict]:
    """-> ({topic: (msgtype, count)}, {topic: [(log time ns, message)]})."""
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conns = {c.topic: (c.msgtype, c.msgcount) for c in reader.connections}
        msgs: dict = {}
        for conn, t_ns, raw in reader.messages():
            msgs.setdefault(conn.topic, []).append((t_ns, reader.deserialize(raw, conn.msgtype)))
    return conns, msgs


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def test_same_seed_gives_identical_world_and_images(world):
    again = generate_world(3, frames=FRAMES, width=SIZE[0], height=SIZE[1])
    np.testing.assert_array_equal(again.poses, world.poses)
    np.testing.assert_array_equal(again.stamps_ns, world.stamps_ns)
    for i in (0, 25, 59):
        np.testing.assert_array_equal(render_frame(again, i), render_frame(world, i))


def test_different_seed_gives_different_world(world):
    other = generate_world(4, frames=FRAMES, width=SIZE[0], height=SIZE[1])
    assert not np.allclose(other.layout.xs, world.layout.xs)
    assert np.abs(render_frame(other, 0).astype(int) - render_frame(world, 0)).mean() > 10


def test_frames_are_rgb_images_of_the_configured_size(world):
    img = render_frame(world, 0)
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    assert img.std() > 20  # a scene, not a blank frame
    assert render_frame(world, 0, size=(64, 48)).shape == (48, 64, 3)
    with pytest.raises(IndexError, match="frame 60 out of range 0..59"):
        render_frame(world, FRAMES)


def test_stamps_are_10_hz(world):
    assert world.stamps_ns.dtype == np.int64
    np.testing.assert_array_equal(np.diff(world.stamps_ns), 100_000_000)
    assert world.stamps[0] == pytest.approx(1_700_000_000.0)


def test_laps_revisit_the_first_lap_within_a_few_metres(world):
    np.testing.assert_array_equal(world.lap, np.repeat([0, 1, 2], 20))
    assert world.loops == 2
    pairs = world.revisit_pairs()
    assert [i for i, _ in pairs] == list(range(20, 60))  # every later frame is a revisit
    for i, j in pairs:
        assert world.lap[j] == 0
        assert math.dist(world.poses[i, :2], world.poses[j, :2]) <= 3.5 + 1e-6
    mid_lap = [(i, j) for i, j in pairs if i % 20 >= 10]  # past the ease-in of each lap
    for i, j in mid_lap:
        turn = abs(math.remainder(world.poses[i, 2] - world.poses[j, 2], math.tau))
        assert math.radians(10) - 1e-6 <= turn <= math.radians(25) + 1e-6


def test_revisit_offsets_are_in_range(world):
    lateral, heading = world.lap_offsets[1:, 0], np.degrees(world.lap_offsets[1:, 1])
    assert np.all((np.abs(lateral) >= 1.0) & (np.abs(lateral) <= 3.0))
    assert np.all((np.abs(heading) >= 10.0) & (np.abs(heading) <= 25.0))
    assert np.all(LANE_OFFSET + lateral >= -3.0)  # stays on the road, clear of parked cars
    assert [lt.name for lt in world.lightings] == ["day", "dusk", "overcast"]


@pytest.mark.parametrize("frames", [FRAMES, 480])
def test_consecutive_frames_move_smoothly(frames):
    moving = generate_world(3, frames=frames)
    step = np.hypot(*np.diff(moving.poses[:, :2], axis=0).T)
    ratio = step / (moving.speed / moving.config.rate_hz)
    # The centre line moves at constant speed; lane offsets stretch or shrink it in corners.
    assert ratio.min() > 0.5 and ratio.max() < 1.5
    turn = np.abs(np.remainder(np.diff(moving.poses[:, 2]) + np.pi, 2 * np.pi) - np.pi)
    max_turn = 60 if frames == FRAMES else 8  # degrees per frame; 60 frames sample coarsely
    assert np.degrees(turn.max()) < max_turn


def test_generate_world_rejects_bad_settings():
    with pytest.raises(ConfigError, match="laps=1: need at least 2 laps"):
        generate_world(1, laps=1)
    with pytest.raises(ConfigError, match=r"frames=10: need at least 8 per lap \(24\)"):
        generate_world(1, frames=10)
    with pytest.raises(ConfigError, match="unknown setting"):
        generate_world(1, colour="red")


def test_mcap_file_reads_back_with_images_camera_info_odometry_and_stamps(tmp_path, world):
    out = write_demo_bag(tmp_path / "demo.mcap", seed=3, frames=FRAMES, size=SIZE)
    assert out == tmp_path / "demo.mcap" and out.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo.mcap"]  # no temp leftovers
    conns, msgs = read_bag(out)
    assert conns == {
        "/camera/image_raw": ("sensor_msgs/msg/Image", FRAMES),
        "/camera/camera_info": ("sensor_msgs/msg/CameraInfo", FRAMES),
        "/camera/depth/image_raw": ("sensor_msgs/msg/Image", FRAMES),
        "/odom": ("nav_msgs/msg/Odometry", FRAMES),
        "/ground_truth": ("nav_msgs/msg/Odometry", FRAMES),
    }
    images, truth = msgs["/camera/image_raw"], msgs["/ground_truth"]
    assert [t for t, _ in images] == world.stamps_ns.tolist()
    for topic in conns:
        assert [stamp_ns(m) for _, m in msgs[topic]] == world.stamps_ns.tolist(), topic
    img = images[7][1]
    assert (img.encoding, img.width, img.height, img.step, img.header.frame_id) == (
        "rgb8",
        160,
        120,
        480,
        "camera",
    )
    np.testing.assert_array_equal(img.data.reshape(120, 160, 3), render_frame(world, 7))
    info = msgs["/camera/camera_info"][7][1]
    assert (info.header.frame_id, info.width, info.height) == ("camera", 160, 120)
    assert info.distortion_model == "plumb_bob" and not info.d.any()
    np.testing.assert_allclose(info.k, [80.0, 0, 79.5, 0, 80.0, 71.5, 0, 0, 1])  # 90 deg hfov
    depth = msgs["/camera/depth/image_raw"][7][1]
    assert (depth.encoding, depth.width, depth.height, depth.step) == ("16UC1", 160, 120, 320)
    assert (depth.header.frame_id, depth.is_bigendian) == ("camera", 0)
    mm = np.frombuffer(depth.data.tobytes(), "<u2").reshape(120, 160)
    expected = render_depth(world.layout, world.poses[7], Camera(160, 120), world.occluders_of(7))
    np.testing.assert_array_equal(mm, depth_to_mm(expected))
    assert (mm[-1] > 0).all() and mm[-1].max() < 5000  # the road just ahead, a few metres
    gt = truth[7][1]
    assert (gt.header.frame_id, gt.child_frame_id) == ("map", "base_link")
    q = gt.pose.pose.orientation
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(world.poses[7, 2])
    xy = np.array([(m.pose.pose.position.x, m.pose.pose.position.y) for _, m in truth])
    np.testing.assert_allclose(xy, world.poses[:, :2])
    for i, j in world.revisit_pairs():  # the ground truth shows the revisits
        assert np.linalg.norm(xy[i] - xy[j]) <= 3.5 + 1e-6
    odom = msgs["/odom"]
    assert (odom[7][1].header.frame_id, odom[7][1].child_frame_id) == ("odom", "base_link")
    drift = np.array([(m.pose.pose.position.x, m.pose.pose.position.y) for _, m in odom]) - xy
    assert np.linalg.norm(drift[0]) == 0.0  # odometry starts at the true pose, then drifts
    assert 0.1 < np.linalg.norm(drift[-1]) < 5.0


def test_drifting_odometry_is_seeded_and_exact_without_noise(world):
    exact = OdometryNoise(scale_error=0.0, yaw_rate_bias_deg_s=0.0, translation_noise=0.0,
                          yaw_noise_deg=0.0)  # fmt: skip
    np.testing.assert_allclose(drifting_odometry(world.poses, 10.0, 3, exact), world.poses,
                               atol=1e-9)  # fmt: skip
    a = drifting_odometry(world.poses, 10.0, 3)
    np.testing.assert_array_equal(a, drifting_odometry(world.poses, 10.0, 3))
    assert not np.array_equal(a, drifting_odometry(world.poses, 10.0, 4))
    scaled = drifting_odometry(world.poses, 10.0, 3, replace(exact, scale_error=0.1))
    length = np.linalg.norm(np.diff(world.poses[:, :2], axis=0), axis=1).sum()
    np.testing.assert_allclose(
        np.linalg.norm(np.diff(scaled[:, :2], axis=0), axis=1).sum(), 1.1 * length
    )
    biased = drifting_odometry(world.poses, 10.0, 3, replace(exact, yaw_rate_bias_deg_s=1.0))
    turned = np.angle(np.exp(1j * (biased[:, 2] - world.poses[:, 2])))
    np.testing.assert_allclose(np.degrees(turned), np.arange(FRAMES) * 0.1, atol=1e-9)
    with pytest.raises(ConfigError, match="translation_noise=.* must be >= 0|must be >= 0"):
        drifting_odometry(world.poses, 10.0, 3, replace(exact, translation_noise=-1.0))
    with pytest.raises(ConfigError, match="scale_error=nan must be finite"):
        drifting_odometry(world.poses, 10.0, 3, replace(exact, scale_error=float("nan")))


def test_camera_to_base_maps_base_points_like_the_renderer():
    cam = Camera()
    x, y, z, qx, qy, qz, qw = camera_to_base(cam)
    rot_bc = np.array([  # quaternion -> rotation matrix
        [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
        [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
        [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
    ])  # fmt: skip
    pose = np.array([3.0, -2.0, 0.7])  # x, y, yaw of base_link
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rot_wb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    point = np.array([10.0, 4.0, 2.5])
    in_base = rot_wb.T @ (point - [pose[0], pose[1], 0.0])
    in_camera = rot_bc.T @ (in_base - [x, y, z])
    np.testing.assert_allclose(in_camera, to_camera(point, pose, cam), atol=1e-12)


def test_compressed_bag_folder_reads_back(tmp_path):
    out = write_demo_bag(tmp_path / "bag", seed=3, frames=24, size=(64, 48), compressed=True)
    assert sorted(p.name for p in out.iterdir()) == ["bag.mcap", "metadata.yaml"]
    conns, msgs = read_bag(out)
    assert conns["/camera/image_raw/compressed"] == ("sensor_msgs/msg/CompressedImage", 24)
    msg = msgs["/camera/image_raw/compressed"][0][1]
    assert msg.format == "jpeg"
    assert cv2.imdecode(msg.data, cv2.IMREAD_COLOR).shape == (48, 64, 3)


def test_mono_bag_holds_the_luma_of_the_colour_bag(tmp_path, capsys):
    argv = ["--seed", "3", "--frames", "24", "--size", "32x24", "--no-depth"]
    assert main([str(tmp_path / "rgb.mcap"), *argv]) == 0
    assert main([str(tmp_path / "mono.mcap"), *argv, "--mono"]) == 0
    assert "24 frames 32x24 (mono8), 3 laps" in capsys.readouterr().out
    rgb = read_bag(tmp_path / "rgb.mcap")[1]["/camera/image_raw"][5][1]
    mono = read_bag(tmp_path / "mono.mcap")[1]["/camera/image_raw"][5][1]
    assert (mono.encoding, mono.step, mono.width, mono.height) == ("mono8", 32, 32, 24)
    colour = rgb.data.reshape(24, 32, 3).astype(np.float64)
    luma = colour @ [0.299, 0.587, 0.114]
    assert np.abs(mono.data.reshape(24, 32) - luma).max() <= 0.51
    jpeg = write_demo_bag(
        tmp_path / "j", seed=3, frames=24, size=(32, 24), compressed=True, mono=True
    )
    msg = read_bag(jpeg)[1]["/camera/image_raw/compressed"][0][1]
    assert cv2.imdecode(msg.data, cv2.IMREAD_UNCHANGED).shape == (24, 32)


def test_existing_output_needs_force(tmp_path):
    out = tmp_path / "demo.mcap"
    out.write_bytes(b"old")
    with pytest.raises(BagError, match="demo.mcap already exists; pass --force"):
        write_demo_bag(out, seed=3, frames=24, size=(32, 24))
    write_demo_bag(out, seed=3, frames=24, size=(32, 24), force=True, depth=False)
    assert read_bag(out)[0]["/odom"] == ("nav_msgs/msg/Odometry", 24)
    assert "/camera/depth/image_raw" not in read_bag(out)[0]
    folder = tmp_path / "notes"
    folder.mkdir()
    (folder / "keep.txt").write_text("mine")
    with pytest.raises(BagError, match="refusing to overwrite .*notes: it is a non-empty folder"):
        write_demo_bag(folder, seed=3, frames=24, size=(32, 24), force=True)
    assert (folder / "keep.txt").read_text() == "mine"


def test_place_dataset_layout(tmp_path):
    root = write_place_dataset(
        tmp_path / "places", seed=3, places=3, views_per_place=4, size=(64, 48)
    )
    assert sorted(p.name for p in root.iterdir()) == ["place_00000", "place_00001", "place_00002"]
    for place in root.iterdir():
        assert sorted(p.name for p in place.iterdir()) == ["0.png", "1.png", "2.png", "3.png"]
    views = [cv2.imread(str(root / "place_00001" / f"{k}.png")) for k in range(4)]
    assert all(v.shape == (48, 64, 3) for v in views)
    assert np.abs(views[0].astype(int) - views[1]).mean() > 3  # views vary
    assert sorted(p.name for p in tmp_path.iterdir()) == ["places"]  # no temp leftovers


def test_place_dataset_is_deterministic_and_force_replaces_it(tmp_path):
    first = write_place_dataset(tmp_path / "a", seed=5, places=1, views_per_place=4, size=(32, 24))
    again = write_place_dataset(tmp_path / "b", seed=5, places=1, views_per_place=4, size=(32, 24))
    for k in range(4):
        name = f"place_00000/{k}.png"
        assert (first / name).read_bytes() == (again / name).read_bytes()
    write_place_dataset(first, seed=6, places=2, views_per_place=4, size=(32, 24), force=True)
    assert sorted(p.name for p in first.iterdir()) == ["place_00000", "place_00001"]
    assert (first / "place_00000/0.png").read_bytes() != (again / "place_00000/0.png").read_bytes()


def test_place_dataset_errors(tmp_path):
    with pytest.raises(ConfigError, match="views_per_place=3: need at least 4"):
        write_place_dataset(tmp_path / "d", places=2, views_per_place=3)
    (tmp_path / "d").mkdir()
    with pytest.raises(DatasetError, match="d already exists; pass --force"):
        write_place_dataset(tmp_path / "d", places=1, views_per_place=4, size=(32, 24))
    (tmp_path / "d" / "readme.txt").write_text("x")
    with pytest.raises(DatasetError, match="refusing to overwrite .*: it is not a place dataset"):
        write_place_dataset(tmp_path / "d", places=1, views_per_place=4, size=(32, 24), force=True)


def test_cli_writes_bag_and_dataset(tmp_path, capsys):
    bag, ds = tmp_path / "demo.mcap", tmp_path / "ds"
    argv = [str(bag), "--seed", "3", "--frames", "24", "--size", "32x24", "--dataset", str(ds)]
    assert main([*argv, "--places", "2", "--views", "4"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"wrote {bag}: 24 frames 32x24 (rgb8), 3 laps = 2 loops, 16 revisit ")
    assert out[1].startswith(f"wrote {ds}: 2 places x 4 views 32x24, seed 3, ")
    assert read_bag(bag)[0]["/camera/image_raw"] == ("sensor_msgs/msg/Image", 24)
    scaled = tmp_path / "scaled.mcap"
    argv = [str(scaled), "--seed", "3", "--frames", "24", "--size", "32x24"]
    assert main([*argv, "--odom-scale-error", "0.5", "--odom-yaw-bias", "0", "--no-depth"]) == 0
    msgs = read_bag(scaled)[1]
    assert "/camera/depth/image_raw" not in msgs and "/camera/depth/image_raw" in read_bag(bag)[1]
    length = {}
    for topic in ("/odom", "/ground_truth"):
        xy = np.array([(m.pose.pose.position.x, m.pose.pose.position.y) for _, m in msgs[topic]])
        length[topic] = np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()
    assert length["/odom"] / length["/ground_truth"] == pytest.approx(1.5, abs=0.02)


@pytest.mark.parametrize(
    ("argv", "code", "message"),
    [
        ([], 2, "error: give an output bag path (OUT) and/or --dataset DIR"),
        (["x.mcap", "--size", "big"], 2, "error: argument --size: invalid size 'big'"),
        (["x.mcap", "--frames", "5"], 1, "error: frames=5: need at least 8 per lap (24)"),
        (["x.mcap", "--size", "8x8"], 1, "error: image size 8x8: each side must be 16-4096"),
        (["--dataset", "d", "--views", "2"], 1, "error: views_per_place=2: need at least 4"),
        (["x.mcap", "--seed", "-1"], 1, "error: seed=-1: must be >= 0"),
        (
            ["x.mcap", "--odom-scale-error", "nan"],
            1,
            "error: odometry noise: scale_error=nan",
        ),
        (
            ["x.mcap", "--odom-scale-error", "-1"],
            1,
            "error: odometry noise: scale_error=-1.0",
        ),
    ],
)
def test_cli_errors(tmp_path, monkeypatch, capsys, argv, code, message):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == code
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x.mcap").exists()


def test_cli_refuses_existing_output(tmp_path, capsys):
    (tmp_path / "x.mcap").write_bytes(b"old")
    assert main([str(tmp_path / "x.mcap"), "--frames", "24", "--size", "32x24"]) == 1
    assert "already exists; pass --force" in capsys.readouterr().err
    assert (tmp_path / "x.mcap").read_bytes() == b"old"
