"""`pairvpr-posegraph`: a bag's odometry + a replay's loops -> optimised trajectory and errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import drives
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.offline.bags.loop_writer import LoopBagWriter
from pair_vpr_ros.offline.bags.opening import jazzy_typestore
from pair_vpr_ros.offline.posegraph.cli import main
from pair_vpr_ros.offline.posegraph.single import run_posegraph
from pair_vpr_ros.offline.report.folder import write_loops_csv, write_loops_json
from pair_vpr_ros.offline.report.loop_io import read_loops
from pair_vpr_ros.offline.report.trajectories import read_tum
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.simulate import ground_truth_loops

CAMERA = " ".join(str(v) for v in drives.CAMERA)


def odometry_msg(ts, stamp: float, pose, frame_id: str):
    t = ts.types
    sec, nsec = divmod(round(stamp * 1e9), 10**9)
    x, y, z, qx, qy, qz, qw = (float(v) for v in pose)
    return t["nav_msgs/msg/Odometry"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id
        ),
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
            ),
            covariance=np.zeros(36),
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](
                linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            ),
            covariance=np.zeros(36),
        ),
    )


def write_odometry_bag(path: Path, stamps, topics: dict[str, np.ndarray]) -> Path:
    ts = jazzy_typestore()
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {
            t: writer.add_connection(t, "nav_msgs/msg/Odometry", typestore=ts) for t in topics
        }
        for i, stamp in enumerate(stamps):
            for topic, poses in topics.items():
                msg = odometry_msg(ts, stamp, poses[i], "map" if topic == "/truth" else "odom")
                writer.write(
                    conns[topic], round(stamp * 1e9), ts.serialize_cdr(msg, msg.__msgtype__)
                )
    return path


def loop_record(factor, accepted: bool = True) -> LoopRecord:
    return LoopRecord(
        query_id=1, query_stamp=factor.query_stamp, query_frame_id="camera", match_id=0,
        match_stamp=factor.match_stamp, match_frame_id="camera", pair_score=1.0,
        global_similarity=0.9, rank_before=1, rank_after=1, accepted=accepted,
        pose_status="metric", pose_inliers=50, tx=factor.translation[0],
        ty=factor.translation[1], tz=factor.translation[2], qx=factor.rotation[0],
        qy=factor.rotation[1], qz=factor.rotation[2], qw=factor.rotation[3],
        covariance=factor.covariance,
    )  # fmt: skip


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A bag with drifting /odom and /truth, and the replay-style outputs of its loops."""
    root = tmp_path_factory.mktemp("world")
    stamps, truth, odometry, pairs = drives.drive()
    factors = ground_truth_loops(stamps, truth, pairs, np.random.default_rng(0),
                                 camera_to_base=drives.CAMERA)  # fmt: skip
    bag = write_odometry_bag(root / "bag", stamps, {"/odom": odometry, "/truth": truth})
    records = [loop_record(f) for f in factors]
    records.append(replace_pose(loop_record(factors[0]), "no depth at the keypoints"))
    records.append(loop_record(factors[1], accepted=False))
    replay = root / "replay"
    replay.mkdir()
    write_loops_json(records, replay / "loops.json")
    write_loops_csv(records, replay / "loops.csv")
    with LoopBagWriter(replay / "bag") as writer:
        for record in records:
            if record.accepted:
                writer.write_loop(record, round(record.query_stamp * 1e9))
    return root, bag, replay, len(factors)


def replace_pose(record: LoopRecord, reason: str) -> LoopRecord:
    from dataclasses import replace

    return replace(record, pose_status="", pose_reason=reason, covariance=())


def test_loop_files_read_alike(world):
    _, _, replay, count = world
    sources = [read_loops(p) for p in (replay, replay / "loops.csv", replay / "bag")]
    assert [len(s.factors) for s in sources] == [count] * 3
    assert sources[0].left_out == {"no depth at the keypoints": 1}
    assert (sources[0].records, sources[0].accepted) == (count + 2, count + 1)
    assert sources[0].factors == sources[1].factors
    for a, b in zip(sources[0].factors, sources[2].factors, strict=True):
        assert a.query_stamp == pytest.approx(b.query_stamp, abs=1e-9)
        np.testing.assert_allclose(a.covariance, b.covariance)


def test_cli_corrects_the_drift(world, tmp_path, capsys):
    _, bag, replay, count = world
    out = tmp_path / "out"
    argv = [str(bag), "--loops", str(replay), "--gt-topic", "/truth", "--out", str(out),
            "--camera-to-base", CAMERA]  # fmt: skip
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert f"loops: {count} loops with a relative pose (0 scale-free) of {count + 1} accepted" in (
        printed
    )
    assert "left out: 1 no depth at the keypoints" in printed
    summary = json.loads((out / "posegraph.json").read_text())
    before = summary["errors"]["odometry"]["ate_rmse"]
    after = summary["errors"]["optimised"]["ate_rmse"]
    assert f"drift (ATE RMSE) odometry {before:.3f} m -> optimised {after:.3f} m" in printed
    assert after < before / 5 and summary["loops_added"] == count
    assert summary["errors"]["optimised"]["rpe_delta_m"] == 10.0
    assert 0.0 < summary["errors"]["optimised"]["rpe_rmse"] < 0.5
    optimised, odometry = read_tum(out / "optimised.tum"), read_tum(out / "odometry.tum")
    assert len(optimised) == len(odometry) == summary["nodes"]
    assert (out / "posegraph.png").read_bytes()[:4] == b"\x89PNG"
    assert len(read_tum(out / "ground_truth.tum")) == 300 + 225


def test_false_loops_injected_are_rejected(world, tmp_path):
    _, bag, replay, count = world
    config = PoseGraphConfig(camera_to_base=drives.CAMERA)
    s = run_posegraph(bag, replay, tmp_path, gt_topic="/truth", config=config,
                      false_loop_fraction=0.1, seed=3)  # fmt: skip
    assert s.loops_injected_false == round(0.1 * count) == s.injected_false_outliers
    assert s.errors["optimised"]["ate_rmse"] < s.errors["odometry"]["ate_rmse"] / 3


def test_no_loops_is_a_warning_and_the_odometry(world, tmp_path, capsys):
    _, bag, _, _ = world
    (tmp_path / "loops.json").write_text("[]")
    argv = [str(bag), "--loops", str(tmp_path / "loops.json"), "--out", str(tmp_path / "o"),
            "--gt-topic", "/truth"]  # fmt: skip
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "warning: no loop closure with a relative pose in" in captured.err
    summary = json.loads((tmp_path / "o" / "posegraph.json").read_text())
    errors = summary["errors"]
    assert errors["optimised"]["ate_rmse"] == pytest.approx(errors["odometry"]["ate_rmse"])


def test_bad_odometry_is_counted(tmp_path):
    stamps, truth, odometry, _ = drives.drive(laps=1)
    odometry = odometry.copy()
    odometry[10, 0] = math.nan
    keep = np.r_[0:50, 80 : len(stamps)]  # a 3 s gap
    bag = write_odometry_bag(tmp_path / "bag", stamps[keep], {"/odom": odometry[keep]})
    (tmp_path / "loops.json").write_text("[]")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "ground_truth.tum").write_text("from an earlier run\n")
    s = run_posegraph(bag, tmp_path / "loops.json", tmp_path / "out")
    assert not (tmp_path / "out" / "ground_truth.tum").exists()  # no --gt-topic this time
    assert s.skipped == {"odometry: pose has NaN or infinite values": 1}
    assert s.odometry_gaps == 1 and s.odometry_messages == len(keep)


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["--odom-topic", "/nope"], 1, "error: topic /nope is not a pose topic of bag"),
        (["--loops", "{tmp}/missing"], 1, "error: loops {tmp}/missing do not exist"),
        (["--loops", "{tmp}/garbage.json"], 1, "is not a JSON list of loop records"),
        (["--loops", "{tmp}/bag"], 1, "has no /loop_closure/factor (nav_msgs/msg/Odometry) topic"),
        (["--inject-false-loops", "0.1"], 1, "error: injecting false loops needs ground truth"),
        (["--camera-to-base", "0 0 1"], 2, "expected 7 numbers 'x y z qx qy qz qw', got 3"),
        (["--node-spacing", "nan"], 2, "--node-spacing: must be a finite number > 0, got 'nan'"),
        (["--inject-false-loops", "-1"], 2, "must be a number from 0 to 10, got '-1'"),
        (["--seed", "1.5"], 2, "argument --seed: must be an integer >= 0, got '1.5'"),
        (["--camera-to-base", "0 0 0 0 0 0 0"], 1, "camera_to_base: pose has a zero quaternion"),
        (["--gt-topic", "/odom", "--params-file", "{tmp}/p.yaml"], 1, "node_spacing_m must be"),
    ],
)
def test_cli_errors(world, tmp_path, capsys, args, code, message):
    root, bag, replay, _ = world
    (tmp_path / "garbage.json").write_text('{"not": "a list"}')
    write_odometry_bag(tmp_path / "bag", [1.0, 2.0], {"/odom": np.tile(drives.CAMERA, (2, 1))})
    (tmp_path / "p.yaml").write_text("/**:\n  ros__parameters:\n    node_spacing_m: fast\n")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    argv = [str(bag), "--loops", str(replay), "--out", str(tmp_path / "o"), *args]
    assert main(argv) == code
    assert message.replace("{tmp}", str(tmp_path)) in capsys.readouterr().err


def test_a_params_file_with_prior_maps_warns_that_they_are_not_read(tmp_path, capsys):
    from argparse import Namespace

    from pair_vpr_ros.offline.posegraph.cli import _config

    path = tmp_path / "p.yaml"
    path.write_text("/**:\n  ros__parameters:\n    prior_map_dirs: ['/maps/a']\n")
    given = Namespace(params_file=path, camera_to_base=None, kernel=None, node_spacing=None)
    assert _config(given) == PoseGraphConfig()
    assert capsys.readouterr().err == (
        "warning: prior_map_dirs is posegraph_node's, not read here: give each session as "
        "--trajectory ROBOT SESSION BAG\n"
    )
