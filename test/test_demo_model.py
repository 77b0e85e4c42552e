"""The shipped demo model loads as a Pair-VPR checkpoint; the demo's parameter file is valid."""

from __future__ import annotations

import json
from pathlib import Path

import torch

import pair_vpr_ros
from pair_vpr_ros.model import load_pairvpr
from pair_vpr_ros.node_params import detector_config, read_params_file

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
    assert (config.top_k, config.exclude_recent_s) == (10, 8.0)
    assert config.keyframe_max_similarity == 1.0
