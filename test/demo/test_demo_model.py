"""The shipped demo model: it loads as a Pair-VPR checkpoint, the demo's parameter file is valid,
and on a short drive through a world it never saw (seed 11: training used 101-112, `make demo`
uses 7, the settings were chosen on 8) it finds the true loop closures and almost no false ones
at the demo's settings. Its measured precision is 0.978 (seed 7); seed 11's 240 frames give 152
true and 0 false (2026-11-26; the model before it: 109 and 1), so the test allows up to 2 false
of >= 100 true. A retrained demo model must pass this again."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

import pair_vpr_ros
from pair_vpr_ros.demo import write_demo_bag
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.model import load_pairvpr
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag
from pair_vpr_ros.params.configs import detector_config
from pair_vpr_ros.params.file import read_params_file

ROOT = Path(pair_vpr_ros.__file__).resolve().parent
ASSET = ROOT / "demo" / "assets" / "demo-small.pth"


def test_demo_model_is_small_and_loads_through_load_pairvpr():
    assert ASSET.stat().st_size <= 5 * 2**20
    model = load_pairvpr(ASSET)
    assert model.config.arch == "small" and model.config.image_size == 112
    summary = json.loads(ASSET.with_suffix(".json").read_text())
    assert summary["parameters"] == sum(t.numel() for t in model.state_dict().values())
    with torch.inference_mode():
        dense, desc = model.encode(torch.zeros(1, 3, 112, 112))
    assert dense.shape == (1, 64, 128) and desc.shape == (1, 512)


def test_demo_parameter_file_is_valid():
    config = detector_config(read_params_file(ROOT.parent / "config" / "demo.yaml"))
    assert (config.top_k, config.exclude_recent_s, config.global_floor) == (5, 8.0, -1.0)
    assert (config.keyframe_max_similarity, config.score_threshold) == (1.0, 64.0)
    assert config.global_weight == 100.0 and config.geometric_verification


@pytest.mark.slow
def test_short_demo_replay_finds_true_loops_and_almost_no_false_ones(tmp_path):
    bag = write_demo_bag(tmp_path / "world.mcap", seed=11, frames=240, depth=False)
    config = detector_config(read_params_file(ROOT.parent / "config" / "demo.yaml"))
    summary = replay_bag(
        bag,
        tmp_path / "out",
        ReplayOptions(pose_topic="/ground_truth", progress=False),
        weights=ASSET,
        config=config,
        geometry=GeometryConfig(relative_pose=False),  # place recognition only: keep it fast
    )
    assert summary.error is None and summary.frames == 240
    ev = summary.evaluation
    assert ev["true_accepted"] >= 100 and ev["false_accepted"] <= 2, ev
