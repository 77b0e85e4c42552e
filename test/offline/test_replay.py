"""replay: end-to-end bag replays with a tiny random-init model, the CLI, and failures part-way.

Revisiting identical images gives identical descriptors even with random weights, so with
``top_k=1`` (no re-ranking choice) and a very low threshold every revisit is accepted as a loop
to its original frame; two new places at the end give two false loops.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from bag_fixtures import (
    IMAGE,
    TS2,
    corrupt_foxglove,
    image_msg,
    revisit_world,
    synthetic_images,
    write_foxglove,
    write_rosbag2,
)
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.messages import loop as loop_messages
from pair_vpr_ros.model import save_pairvpr
from pair_vpr_ros.offline.bags import loop_writer as loop_bag
from pair_vpr_ros.offline.replay import run as replay
from pair_vpr_ros.offline.replay.cli import main
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag
from pair_vpr_ros.place_map import PlaceMap

CONFIG = DetectorConfig(
    top_k=1, score_threshold=-1e9, keyframe_max_similarity=1.0,
    exclude_recent_s=30.0, exclude_recent_keyframes=0,
)  # fmt: skip
QUIET = ReplayOptions(progress=False)


def test_replay_end_to_end(tmp_path, tiny_model):
    images, poses = revisit_world()
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    out = tmp_path / "out"
    s = replay_bag(
        bag, out, ReplayOptions(write_bag=True, progress=False), model=tiny_model, config=CONFIG
    )
    assert s.error is None and s.warnings == []
    assert (s.topic, s.pose_topic) == ("/cam/image", "/odom")
    assert (s.frames, s.keyframes, s.candidates, s.loops, s.skipped) == (17, 17, 7, 7, 0)
    assert s.line().startswith("frames 17, keyframes 17, loops 7, skipped 0, ")
    assert s.pipeline_counts == dict(
        rate_limited=0, encoded=17, similar_to_keyframe=0, keyframes=17, represented=0, loops=7,
        rejected=0, pose_metric=0, pose_metric_odometry=0, pose_scale_free=0, pose_none=7,
        depth_wrong_size=0, intrinsics_wrong_size=0, features_damaged=0, candidates_scored=7,
        decoder_passes=14, rerank_budget_cut=0, rerank_skipped=0, rerank_covered=7, clock_jumps=0,
        stereo_depth=0, stereo_invalid=0,
        map_searches_skipped=0, map_keyframes_pending=0,
    )  # fmt: skip
    ev = s.evaluation
    assert (ev["positives"], ev["true_accepted"], ev["false_accepted"]) == (5, 5, 2)
    assert ev["precision"] == 5 / 7 and ev["recall"] == 1.0 and ev["exclusion_s"] == 30.0
    assert ev["global_only"]["recall_at_100_precision"] == 1.0
    whole = s.loop_evaluation  # the same evaluation with its curves, for library callers
    assert {**whole.to_dict(), "gt_topic": "/odom"} == ev
    top = whole.reranked.recall_at_precision(1.0)
    assert (
        top == ev["reranked"]["recall_at_100_precision"] and "loop_evaluation" not in s.to_dict()
    )

    loops = json.loads((out / "loops.json").read_text())
    assert [(r["query_id"], r["match_id"]) for r in loops][:5] == [(i + 10, i) for i in range(5)]
    assert [r["query_stamp"] for r in loops] == [100.0, 101.0, 102.0, 103.0, 104.0, 105.0, 106.0]
    assert (out / "loops.csv").read_text().count("\n") == 8
    assert json.loads((out / "summary.json").read_text()) == json.loads(json.dumps(s.to_dict()))
    assert (out / "pr_curve.png").stat().st_size > 0 and (
        out / "trajectory.png"
    ).stat().st_size > 0

    with PlaceMap.load(out / "map", expected_fingerprint=tiny_model.fingerprint) as loaded:
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
    typed = [m for _, m in got["/loop_closure/typed"]]  # what the node publishes there
    assert len(typed) == 7 and typed[0].__msgtype__ == loop_messages.TYPED_TYPE
    assert (typed[0].query_id, typed[0].match_id, typed[0].accepted) == (10, 0, True)
    assert (typed[0].query_stamp.sec, typed[0].header.stamp.sec) == (100, 100)
    assert typed[0].pose_status == typed[0].POSE_NONE == 0
    assert typed[0].global_similarity == loops[0]["global_similarity"]
    assert np.isnan(typed[0].relative_pose.covariance).all()


def test_replay_without_poses_and_map(tmp_path, tiny_model):
    images, _ = revisit_world()
    bag = write_foxglove(tmp_path / "f.mcap", images[:12])  # CompressedImage, no poses
    out = tmp_path / "out"
    s = replay_bag(
        bag,
        out,
        ReplayOptions(save_map=False, max_frames=11, progress=False),
        model=tiny_model,
        config=CONFIG,
    )
    assert (s.frames, s.loops, s.pose_topic, s.evaluation, s.map_dir) == (11, 1, None, None, None)
    # no plots, no suggested parameters (no ground truth); the report's pages all the same
    assert sorted(p.name for p in out.iterdir()) == [
        "loops.csv", "loops.json", "report", "summary.json",
    ]  # fmt: skip


def test_bad_images_are_counted(tmp_path, tiny_model):
    a, b = synthetic_images(2)
    bad = image_msg(TS2, 2.0, a, compressed=False, encoding="no_such_encoding")
    bag = write_rosbag2(
        tmp_path / "bag", [(1.0, a), (3.0, b)], extra=[("/cam/image", IMAGE, bad, 2.0)]
    )
    s = replay_bag(bag, tmp_path / "out", QUIET, model=tiny_model, config=CONFIG)
    assert (s.frames, s.skipped, s.keyframes) == (3, 1, 2)
    (reason,) = s.skip_reasons
    assert "no_such_encoding" in reason and s.skip_reasons[reason] == 1


def test_non_finite_pose_is_skipped_not_fatal(tmp_path, tiny_model):
    """Issue 13 #5: one NaN pose used to stop the replay with nothing written."""
    images, poses = revisit_world()
    poses[3] = (3.0, (float("nan"), 0.0, 0.0))
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    s = replay_bag(bag, tmp_path / "out", QUIET, model=tiny_model, config=CONFIG)
    assert s.error is None and s.bad_poses == 1 and s.keyframes == 17
    assert s.warnings == [
        "1 poses of /odom hold NaN or infinite values and were skipped (the first at stamp "
        "3.000 s); frames near them have no pose"
    ]
    with PlaceMap.load(tmp_path / "out" / "map") as loaded:
        assert loaded.meta(3).pose is None and loaded.meta(4).pose is not None
    assert s.evaluation is not None  # the other keyframes are still evaluated


def test_stamps_going_back_are_warned_about(tmp_path, tiny_model):
    images = [(t, rgb) for t, rgb in zip([1.0, 2.0, 2.0, 1.5], synthetic_images(4), strict=True)]
    extra = [("/cam/image", IMAGE, image_msg(TS2, t, rgb, False), 10.0 + i)
             for i, (t, rgb) in enumerate(images)]  # fmt: skip
    bag = write_rosbag2(tmp_path / "bag", [], extra=extra)
    s = replay_bag(bag, tmp_path / "out", QUIET, model=tiny_model, config=CONFIG)
    assert (s.stamps_backwards, s.stamps_repeated, s.keyframes) == (1, 1, 4)
    assert [w.split(" (")[0] for w in s.warnings] == [
        "1 image stamps of /cam/image go back in time",
        "1 image stamps of /cam/image repeat the previous one",
    ]


def _corrupt_bag(tmp_path):
    return corrupt_foxglove(tmp_path / "c.mcap", revisit_world()[0])


def test_failure_part_way_keeps_what_was_processed(tmp_path, tiny_model):
    out = tmp_path / "out"
    s = replay_bag(_corrupt_bag(tmp_path), out, QUIET, model=tiny_model, config=CONFIG)
    assert 0 < s.frames < 17
    assert f"stopped at image message {s.frames} (after stamp " in s.error
    assert "Chunk checksum mismatch" in s.error
    assert s.keyframes == s.frames  # every frame read before the failure was processed
    saved = json.loads((out / "summary.json").read_text())
    assert saved["error"] == s.error and saved["frames"] == s.frames
    with PlaceMap.load(out / "map") as loaded:
        assert len(loaded) == s.frames


@pytest.fixture(scope="module")
def weights(tmp_path_factory, tiny_model):
    return save_pairvpr(tiny_model, tmp_path_factory.mktemp("w") / "tiny.pth")


def test_cli_success(tmp_path, weights, capsys):
    images, poses = revisit_world()
    bag = write_rosbag2(tmp_path / "bag", images, poses, storage="sqlite3")
    out = tmp_path / "out"
    argv = [str(bag), "--weights", str(weights), "--out", str(out), "--quiet"]
    assert main(argv + ["--top-k", "1", "--threshold=-1e9", "--batch-size", "3"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[-1].startswith("frames 17, keyframes ")
    assert printed[-1].endswith(" frames/s")
    assert printed[-2] == f"outputs in {out}"
    assert printed[:2] == [  # the pose topic found, said
        "keyframe poses: /odom, the bag's only pose topic (choose with --pose-topic, or "
        "--pose-topic none)",
        "ground truth: /odom, the keyframe pose topic (odometry drifts: pass --gt-topic for "
        "true poses)",
    ]
    assert printed[2].startswith("precision ") and printed[2].endswith("ground truth /odom)")
    assert printed[3].startswith("suggested score_threshold ")  # with ground truth (#45)
    assert printed[4] == f"report: {out / 'report' / 'index.html'} (open it in a browser)"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["notes"][:2] == printed[:2]
    assert summary["frames"] == 17 and summary["map_dir"] == str((out / "map").resolve())


def test_cli_errors(tmp_path, weights, capsys):
    missing = tmp_path / "nope.mcap"
    assert main([str(missing), "--weights", str(weights), "--out", str(tmp_path / "o")]) == 1
    assert capsys.readouterr().err == (
        f"error: bag {missing} does not exist: give a rosbag2 folder, a .mcap or .db3 file "
        "or a ROS 1 .bag\n"
    )
    bag = write_rosbag2(tmp_path / "bag", revisit_world()[0][:2])
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
    assert main(args) == 2  # a bad flag value is a usage error (see test_bad_input_replay.py)
    assert capsys.readouterr().err.endswith(
        "error: argument --threshold: must be a finite number, got 'nan'\n"
    )


def test_cli_device_errors(tmp_path, weights, capsys):
    bag = write_rosbag2(tmp_path / "bag", revisit_world()[0][:2])
    args = [str(bag), "--weights", str(weights), "--out", str(tmp_path / "o")]
    assert main([*args, "--device", "gpu9"]) == 1
    assert capsys.readouterr().err == (
        "error: device 'gpu9' is not a torch device (auto, cpu, cuda, cuda:1)\n"
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
    images, poses = revisit_world()
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    params = tmp_path / "params.yaml"
    params.write_text(
        "/**:\n  ros__parameters:\n    top_k: 1\n    score_threshold: -900000.0\n"
        "    rerank_budget_ms: 40.0\n    exclude_recent_s: 1.0\n    keyframe_max_similarity: 1.0\n"
    )
    out = tmp_path / "out"
    argv = [str(bag), "--weights", str(weights), "--out", str(out), "--quiet"]
    assert main(argv + ["--params-file", str(params), "--threshold=-5e5"]) == 0
    capsys.readouterr()
    saved = json.loads((out / "summary.json").read_text())
    assert saved["config"]["top_k"] == 1 and saved["config"]["score_threshold"] == -5e5
    assert saved["config"]["rerank_budget_ms"] == 40.0
    records = json.loads((out / "loops.json").read_text())
    scored = sum(r["scored"] for r in records)
    assert saved["pipeline_counts"]["candidates_scored"] == scored > 0
    flags = ["--params-file", str(params), "--rerank-budget-ms", "0", "--overwrite"]
    assert main(argv + flags) == 0
    assert json.loads((out / "summary.json").read_text())["config"]["rerank_budget_ms"] == 0.0
    params.write_text("/**:\n  ros__parameters:\n    top_k: many\n")
    assert main(argv + ["--params-file", str(params)]) == 1
    assert capsys.readouterr().err == (
        f"error: parameter file {params}: top_k must be an integer, got 'many'\n"
    )


def test_cli_ctrl_c_writes_outputs_and_exits_130(tmp_path, weights, capsys, monkeypatch):
    bag = write_rosbag2(tmp_path / "bag", *revisit_world())
    real = LoopClosurePipeline.process_many

    def interrupted(self, frames, batch_size):
        for n, outcome in enumerate(real(self, frames, batch_size)):
            if n == 4:
                raise KeyboardInterrupt
            yield outcome

    monkeypatch.setattr(LoopClosurePipeline, "process_many", interrupted)
    out = tmp_path / "o"
    assert main([str(bag), "--weights", str(weights), "--out", str(out), "--quiet"]) == 130
    assert capsys.readouterr().err.startswith("error: interrupted after ")
    saved = json.loads((out / "summary.json").read_text())
    assert saved["interrupted"] and saved["error"].startswith("interrupted after ")
    assert 4 < saved["frames"] < 17
    with PlaceMap.load(out / "map") as loaded:
        assert len(loaded) == saved["keyframes"] > 0


def test_weights_from_the_environment_and_nothing_else(tmp_path, weights, capsys, monkeypatch):
    bag = write_rosbag2(tmp_path / "bag", *revisit_world())
    monkeypatch.chdir(tmp_path)
    assert main([str(bag), "--quiet"]) == 1  # no weights anywhere (see test/conftest.py)
    err = capsys.readouterr().err
    assert err.startswith("error: no Pair-VPR weights found; looked in --weights: not given; ")
    assert err.count("\n") == 1 and not (tmp_path / "replay_out").exists()
    monkeypatch.setenv("PAIRVPR_WEIGHTS", str(weights))
    assert main([str(bag)]) == 0  # outputs at their default place
    assert capsys.readouterr().out.splitlines()[-2] == "outputs in replay_out"
    summary = json.loads((tmp_path / "replay_out" / "summary.json").read_text())
    assert summary["frames"] == 17 and summary["model"].startswith("sha256:")
    assert summary["threads"] == 1  # --threads auto: a tiny network runs on one thread
    assert (tmp_path / "replay_out" / "map").is_dir()


@pytest.mark.parametrize(
    "flags, in_params_file, want",
    [
        ([], None, "auto"),
        (["--openvino-cache-dir", "none"], None, ""),
        (["--openvino-cache-dir", "/ov"], None, "/ov"),
        ([], "/from/file", "/from/file"),
        (["--openvino-cache-dir", ""], "/from/file", ""),
    ],
)
def test_cli_openvino_cache_dir(tmp_path, monkeypatch, tiny_model, flags, in_params_file, want):
    """--openvino-cache-dir (else the parameter file's openvino_cache_dir, else auto) reaches
    the model loader: 'none' or '' turn the cache off."""
    seen = {}

    def loader(weights, **kwargs):
        seen.update(kwargs)
        return tiny_model

    monkeypatch.setattr(replay, "load_model", loader)
    bag = write_rosbag2(tmp_path / "bag", revisit_world()[0][:2])
    argv = [str(bag), "--weights", "random-tiny", "--out", str(tmp_path / "o"), "--quiet"]
    if in_params_file is not None:
        params = tmp_path / "p.yaml"
        params.write_text(
            f"/**:\n  ros__parameters:\n    openvino_cache_dir: '{in_params_file}'\n"
        )
        argv += ["--params-file", str(params)]
    assert main([*argv, "--backend", "openvino", *flags]) == 0
    assert seen["openvino_cache_dir"] == want and seen["backend"] == "openvino"


def test_replay_cli_runs_as_a_module(tmp_path) -> None:
    """`python -m pair_vpr_ros.offline.replay.cli` is the console script (the recipe uses it)."""
    bag = tmp_path / "none.mcap"
    run = subprocess.run(
        [sys.executable, "-m", "pair_vpr_ros.offline.replay.cli", str(bag)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 1
    assert run.stderr.startswith(f"error: bag {bag} does not exist")


@pytest.mark.parametrize("definition", ["missing", "broken"])
def test_output_bag_without_the_typed_definition(tmp_path, tiny_model, monkeypatch, definition):
    """No LoopClosure.msg to be found (or one that does not parse): the bag is written without
    /loop_closure/typed, and the summary says why."""
    broken = tmp_path / "LoopClosure.msg"
    broken.write_text("int32 x\nfoo/Bar[ y\n")
    monkeypatch.setattr(loop_bag, "jazzy_typestore", lambda: get_typestore(Stores.ROS2_JAZZY))
    monkeypatch.setattr(
        loop_bag, "typed_definition", lambda: broken if definition == "broken" else None
    )
    images, poses = revisit_world()
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    opts = ReplayOptions(write_bag=True, progress=False, save_map=False)
    s = replay_bag(bag, tmp_path / "out", opts, model=tiny_model, config=CONFIG)
    assert s.error is None and s.loops == 7
    why = (
        "was not found (build pair_vpr_ros_interfaces"
        if definition == "missing"
        else f"cannot read {broken}: "
    )
    assert len(s.warnings) == 1 and s.warnings[0].startswith("/loop_closure/typed is not written")
    assert why in s.warnings[0]
    with AnyReader([tmp_path / "out" / "bag"]) as reader:
        topics = {c.topic for c in reader.connections}
    assert "/loop_closure/typed" not in topics and "/loop_closure/json" in topics
