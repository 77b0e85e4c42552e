"""replay: end-to-end bag replays with a tiny random-init model, the CLI, and failures part-way.

Revisiting identical images gives identical descriptors even with random weights, so with
``top_k=1`` (no re-ranking choice) and a very low threshold every revisit is accepted as a loop
to its original frame; two new places at the end give two false loops.
"""

from __future__ import annotations

import json

import pytest
import torch
from bag_fixtures import IMAGE, TS2, image_msg, synthetic_images, write_foxglove, write_rosbag2
from rosbags.highlevel import AnyReader

from pair_vpr_ros import loop_messages
from pair_vpr_ros.detector import DetectorConfig
from pair_vpr_ros.model import ModelConfig, build_pairvpr, save_pairvpr
from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.replay import main, replay_bag

CONFIG = DetectorConfig(
    top_k=1, score_threshold=-1e9, keyframe_max_similarity=1.0,
    exclude_recent_s=30.0, exclude_recent_keyframes=0,
)  # fmt: skip


@pytest.fixture(scope="module")
def model():
    torch.manual_seed(0)
    return build_pairvpr(ModelConfig.tiny())


def _world():
    """10 places at 1 Hz (20 m apart), revisits of places 0-4 at t=100.., two new places."""
    imgs = synthetic_images(12, size=32)
    images = [(float(i), imgs[i]) for i in range(10)]
    poses = [(float(i), (20.0 * i, 0.0, 0.0)) for i in range(10)]
    images += [(100.0 + i, imgs[i]) for i in range(5)]
    poses += [(100.0 + i, (20.0 * i, 0.0, 0.0)) for i in range(5)]
    images += [(105.0, imgs[10]), (106.0, imgs[11])]
    poses += [(105.0, (500.0, 500.0, 0.0)), (106.0, (600.0, 500.0, 0.0))]
    return images, poses


def test_replay_end_to_end(tmp_path, model):
    images, poses = _world()
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    out = tmp_path / "out"
    s = replay_bag(bag, out, model=model, config=CONFIG, write_bag=True, progress=False)
    assert s.error is None and s.warnings == []
    assert (s.topic, s.pose_topic) == ("/cam/image", "/odom")
    assert (s.frames, s.keyframes, s.candidates, s.loops, s.skipped) == (17, 17, 7, 7, 0)
    assert s.line().startswith("frames 17, keyframes 17, loops 7, skipped 0, ")
    ev = s.evaluation
    assert (ev["positives"], ev["true_accepted"], ev["false_accepted"]) == (5, 5, 2)
    assert ev["precision"] == 5 / 7 and ev["recall"] == 1.0 and ev["exclusion_s"] == 30.0
    assert ev["global_only"]["recall_at_100_precision"] == 1.0

    loops = json.loads((out / "loops.json").read_text())
    assert [(r["query_id"], r["match_id"]) for r in loops][:5] == [(i + 10, i) for i in range(5)]
    assert [r["query_stamp"] for r in loops] == [100.0, 101.0, 102.0, 103.0, 104.0, 105.0, 106.0]
    assert (out / "loops.csv").read_text().count("\n") == 8
    assert json.loads((out / "summary.json").read_text()) == json.loads(json.dumps(s.to_dict()))
    assert (out / "pr_curve.png").stat().st_size > 0 and (
        out / "trajectory.png"
    ).stat().st_size > 0

    with PlaceMap.load(out / "map", expected_fingerprint=model.fingerprint) as loaded:
        assert len(loaded) == 17
        assert loaded.meta(3).pose == (60.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
        assert loaded.meta(3).stamp == 3.0

    with AnyReader([out / "bag"]) as reader:
        got: dict[str, list] = {}
        for c, t, raw in reader.messages():
            got.setdefault(c.topic, []).append((t, reader.deserialize(raw, c.msgtype)))
    assert len(got["/cam/image"]) == 17
    pairs = [(t, m.data.tolist()) for t, m in got["/loop_closure"]]
    assert pairs[:2] == [(100 * 10**9, [100.0, 0.0]), (101 * 10**9, [101.0, 1.0])]
    assert len(pairs) == 7 and all(len(data) == 2 for _, data in pairs)
    details = [m for _, m in got["/loop_closure/detail"]]
    first = loop_messages.detail_to_dict([d.label for d in details[0].layout.dim], details[0].data)
    assert (first["query_id"], first["match_id"], first["accepted"]) == (10.0, 0.0, 1.0)
    assert json.loads(got["/loop_closure/json"][0][1].data) == loops[0]


def test_replay_without_poses_and_map(tmp_path, model):
    images, _ = _world()
    bag = write_foxglove(tmp_path / "f.mcap", images[:12])  # CompressedImage, no poses
    out = tmp_path / "out"
    s = replay_bag(
        bag, out, model=model, config=CONFIG, save_map=False, max_frames=11, progress=False
    )
    assert (s.frames, s.loops, s.pose_topic, s.evaluation, s.map_dir) == (11, 1, None, None, None)
    assert sorted(p.name for p in out.iterdir()) == ["loops.csv", "loops.json", "summary.json"]


def test_bad_images_are_counted(tmp_path, model):
    a, b = synthetic_images(2)
    bad = image_msg(TS2, 2.0, a, compressed=False, encoding="no_such_encoding")
    bag = write_rosbag2(
        tmp_path / "bag", [(1.0, a), (3.0, b)], extra=[("/cam/image", IMAGE, bad, 2.0)]
    )
    s = replay_bag(bag, tmp_path / "out", model=model, config=CONFIG, progress=False)
    assert (s.frames, s.skipped, s.keyframes) == (3, 1, 2)
    (reason,) = s.skip_reasons
    assert "no_such_encoding" in reason and s.skip_reasons[reason] == 1


def _corrupt_bag(tmp_path):
    images, _ = _world()
    path = write_foxglove(tmp_path / "c.mcap", images, compressed=False, chunk_size=3000)
    data = bytearray(path.read_bytes())
    for k in range(len(data) // 2, len(data) // 2 + 64):
        data[k] ^= 0xFF
    path.write_bytes(bytes(data))
    return path


def test_failure_part_way_keeps_what_was_processed(tmp_path, model):
    out = tmp_path / "out"
    s = replay_bag(_corrupt_bag(tmp_path), out, model=model, config=CONFIG, progress=False)
    assert 0 < s.frames < 17
    assert f"stopped at image message {s.frames} (after stamp " in s.error
    assert "Chunk checksum mismatch" in s.error
    assert s.keyframes == s.frames  # every frame read before the failure was processed
    saved = json.loads((out / "summary.json").read_text())
    assert saved["error"] == s.error and saved["frames"] == s.frames
    with PlaceMap.load(out / "map") as loaded:
        assert len(loaded) == s.frames


@pytest.fixture(scope="module")
def weights(tmp_path_factory, model):
    return save_pairvpr(model, tmp_path_factory.mktemp("w") / "tiny.pth")


def test_cli_success(tmp_path, weights, capsys):
    images, poses = _world()
    bag = write_rosbag2(tmp_path / "bag", images, poses, storage="sqlite3")
    out = tmp_path / "out"
    argv = [str(bag), "--weights", str(weights), "--out", str(out), "--quiet"]
    assert main(argv + ["--top-k", "1", "--threshold=-1e9", "--batch-size", "3"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[-1].startswith("frames 17, keyframes ")
    assert printed[-1].endswith(" frames/s")
    assert printed[-2] == f"outputs in {out}"
    assert printed[0].startswith("precision ")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 17 and summary["map_dir"] == str((out / "map").resolve())


def test_cli_errors(tmp_path, weights, capsys):
    missing = tmp_path / "nope.mcap"
    assert main([str(missing), "--weights", str(weights), "--out", str(tmp_path / "o")]) == 1
    assert capsys.readouterr().err == (
        f"error: bag {missing} does not exist: give a rosbag2 folder, a .mcap or .db3 file "
        "or a ROS 1 .bag\n"
    )
    bag = write_rosbag2(tmp_path / "bag", _world()[0][:2])
    out = ["--out", str(tmp_path / "o")]
    assert main([str(bag), "--weights", str(tmp_path / "no.pth"), *out]) == 1
    assert capsys.readouterr().err.startswith(f"error: checkpoint {tmp_path / 'no.pth'} does not ")
    args = [str(bag), "--weights", str(weights), "--topic", "/x", *out]
    assert main(args) == 1
    assert "error: topic /x is not an image topic" in capsys.readouterr().err
    args = [
        str(bag),
        "--weights",
        str(weights),
        "--threshold",
        "nan",
        "--out",
        str(tmp_path / "o"),
    ]
    assert main(args) == 1
    assert capsys.readouterr().err == (
        "error: detector score_threshold=nan must be a finite number\n"
    )


def test_cli_device_errors(tmp_path, weights, capsys):
    bag = write_rosbag2(tmp_path / "bag", _world()[0][:2])
    args = [str(bag), "--weights", str(weights), "--out", str(tmp_path / "o")]
    assert main([*args, "--device", "gpu9"]) == 1
    assert capsys.readouterr().err == (
        "error: device 'gpu9' is not a torch device (cpu, cuda, cuda:1)\n"
    )
    if not torch.cuda.is_available():
        assert main([*args, "--device", "cuda"]) == 1
        assert capsys.readouterr().err == (
            "error: device 'cuda': CUDA is not available here; use cpu\n"
        )


def test_cli_failure_part_way(tmp_path, weights, capsys):
    args = [str(_corrupt_bag(tmp_path)), "--weights", str(weights), "--out", str(tmp_path / "o")]
    assert main(args + ["--quiet", "--map-dir", "none"]) == 1
    captured = capsys.readouterr()
    assert captured.err.startswith("error: reading /cam/image/compressed")
    assert "stopped at image message" in captured.err
    assert captured.err.endswith("(what was processed before is written)\n")
    assert captured.out.splitlines()[-1].startswith("frames ")
    assert not (tmp_path / "o" / "map").exists()


def test_cli_params_file(tmp_path, weights, capsys):
    images, poses = _world()
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    top_k: 1\n    score_threshold: -900000.0\n")
    out = tmp_path / "out"
    argv = [str(bag), "--weights", str(weights), "--out", str(out), "--quiet"]
    assert main(argv + ["--params-file", str(params), "--threshold=-5e5"]) == 0
    capsys.readouterr()
    saved = json.loads((out / "summary.json").read_text())
    assert saved["config"]["top_k"] == 1 and saved["config"]["score_threshold"] == -5e5
    params.write_text("/**:\n  ros__parameters:\n    top_k: many\n")
    assert main(argv + ["--params-file", str(params)]) == 1
    assert capsys.readouterr().err == (
        f"error: parameter file {params}: top_k must be an integer, got 'many'\n"
    )
