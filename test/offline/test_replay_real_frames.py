"""A rosbag2 of the 8 real TUM RGB-D frames (colour, 16UC1 depth, camera_info with the lens
distortion, /ground_truth) replayed with every top-1 accepted: every loop gets a metric pose
near its covariance of the motion-capture truth (test/real_frames.py, CC BY 4.0 data)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from bag_fixtures import TS2, _header, write_rosbag2
from real_frames import TUM, TUM_D, TUM_K, chi2, tum_frames
from test_replay_geometry import CONFIG, depth_msg

from pair_vpr_ros.geometry.rotations import matrix_quaternion, quaternion_matrix
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag

INFO, POSE = "sensor_msgs/msg/CameraInfo", "geometry_msgs/msg/PoseStamped"


def _stamps() -> list[float]:
    """The colour frames' stamps, s since 1305031233 (small: exact in the bag's nanoseconds)."""
    lines = (TUM / "associations.txt").read_text().splitlines()
    return [float(f.split()[0]) - 1305031233.0 for f in lines if f and not f.startswith("#")]


def _info(stamp: float):
    fx, fy, cx, cy = TUM_K
    roi = TS2.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return TS2.types[INFO](
        header=_header(TS2, stamp, "cam"), height=480, width=640, distortion_model="plumb_bob",
        d=np.array(TUM_D), k=np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1.0]), r=np.eye(3).ravel(),
        p=np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1.0, 0]), binning_x=0, binning_y=0,
        roi=roi,
    )  # fmt: skip


def _pose(stamp: float, t_world_cam: np.ndarray):
    g = "geometry_msgs/msg/"
    x, y, z, w = matrix_quaternion(t_world_cam[:3, :3])
    pose = TS2.types[g + "Pose"](
        position=TS2.types[g + "Point"](*map(float, t_world_cam[:3, 3])),
        orientation=TS2.types[g + "Quaternion"](x=x, y=y, z=z, w=w),
    )
    return TS2.types[POSE](header=_header(TS2, stamp, "map"), pose=pose)


@pytest.fixture
def tum_bag(tmp_path):
    stamps, frames = _stamps(), tum_frames()
    images = [(t, rgb) for t, (rgb, _, _) in zip(stamps, frames, strict=True)]
    extra = [("/cam/camera_info", INFO, _info(stamps[0] - 0.01), stamps[0] - 0.01)]
    for t, (_, depth, pose) in zip(stamps, frames, strict=True):
        mm = np.nan_to_num(depth * 1000.0, nan=0.0).round().astype(np.uint16)
        extra += [("/cam/depth", "sensor_msgs/msg/Image", depth_msg(t + 0.005, mm), t + 0.005),
                  ("/ground_truth", POSE, _pose(t, pose), t)]  # fmt: skip
    by_stamp = dict(zip(stamps, frames, strict=True))
    return write_rosbag2(tmp_path / "bag", images, extra=extra), by_stamp


def test_tum_bag_replay_poses_every_loop_within_its_covariance(tmp_path, tiny_model, tum_bag):
    bag, by_stamp = tum_bag
    options = ReplayOptions(progress=False, overwrite=True, gt_topic="/ground_truth")
    config = replace(CONFIG, global_floor=-1.0)  # every top-1 is accepted
    s = replay_bag(bag, tmp_path / "out", options, model=tiny_model, config=config)
    loops = [r for r in json.loads((tmp_path / "out" / "loops.json").read_text()) if r["accepted"]]
    assert s.camera_info_topic == "/cam/camera_info" and len(loops) >= 5
    chi2s = []
    for r in loops:
        assert r["pose_status"] == "metric", r["pose_reason"]
        pq = by_stamp[min(by_stamp, key=lambda t: abs(t - r["query_stamp"]))][2]
        pm = by_stamp[min(by_stamp, key=lambda t: abs(t - r["match_stamp"]))][2]
        truth = np.linalg.inv(pm) @ pq
        rot = quaternion_matrix([r["qx"], r["qy"], r["qz"], r["qw"]])
        cov = np.array(r["covariance"]).reshape(6, 6)
        chi2s.append(chi2(truth, rot, np.array([r["tx"], r["ty"], r["tz"]]), cov)[0])
    # Calibrated in the median (6 dof: 5.3), no loop a tight wrong factor. The top-1 pairs are
    # 3-2, 4-1, 5-3, 6-4, 7-2: the checks widen the first four (PnP and the essential matrix
    # disagree, the rows disagree); 7-2 (30 inliers, compact features) is 0.56 deg off at a
    # stated 0.1 deg, chi-square 61, an error no check of its data shows: what
    # pose_systematic_px is for on this rolling-shutter camera (docs/real-cameras.md).
    assert np.median(chi2s) < 12.0 and max(chi2s) < 100.0, chi2s
