"""The node's parameter table (ROS-free): YAML mirror, validation, detector config."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import pytest
import yaml

from pair_vpr_ros import params
from pair_vpr_ros.loops.detector import DetectorConfig

CONFIG = Path(__file__).resolve().parents[2] / "config" / "vpr_node.yaml"


def test_config_file_mirrors_the_declared_parameters():
    loaded = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]
    assert list(loaded) == [p.name for p in params.PARAMS]
    for name, default in params.defaults().items():
        value = tuple(loaded[name]) if isinstance(default, tuple) else loaded[name]  # YAML list
        assert value == default and type(value) is type(default), name
    assert CONFIG.read_text() == params.yaml_text()


def test_detector_defaults_match_the_detector_config():
    base = DetectorConfig()
    explicit = {"top_k", "min_frame_interval", "preset"}  # 0 / -1 / name: taken from the preset
    for name in params.DETECTOR_PARAMS:
        if name not in explicit:
            assert params.SPECS[name].default == getattr(base, name), name
    assert set(params.DETECTOR_PARAMS) - {"preset"} <= {f.name for f in fields(DetectorConfig)}


def test_preset_values_apply_unless_overridden():
    v = params.defaults()
    cfg = params.detector_config(v)
    assert (cfg.top_k, cfg.min_frame_interval, cfg.mode) == (10, 0.2, "mapping")
    cfg = params.detector_config({**v, "preset": "performance", "min_frame_interval": 0.5})
    assert (cfg.top_k, cfg.min_frame_interval) == (100, 0.5)
    assert params.detector_config({**v, "top_k": 3}).top_k == 3


@pytest.mark.parametrize(
    "name, value, reason",
    [
        ("top_k", -1, "top_k=-1 is out of range [0, 1000]"),
        ("top_k", 2.5, "top_k must be an integer, got 2.5"),
        ("top_k", True, "top_k must be an integer, got True"),
        ("score_threshold", float("inf"), "score_threshold must be a finite number, got inf"),
        ("global_floor", 1.5, "global_floor=1.5 is out of range [-1.0, 1.0]"),
        ("precision", "int4", "precision='int4' must be one of fp32, int8, bf16, fp16"),
        ("backend", "openvno", "backend='openvno' must be one of torch, openvino"),
        ("image_size", 300, "image_size=300 must be 0 or a multiple of 14 (e.g. 224, 322)"),
        ("no_such", 1, "unknown parameter 'no_such'"),
    ],
)
def test_bad_values_are_explained(name, value, reason):
    assert params.check_value(name, value) == reason


def test_valid_values_pass():
    valid = [("top_k", 0), ("score_threshold", 3), ("image_size", 322), ("qos", "reliable")]
    for name, value in valid:
        assert params.check_value(name, value) is None


def test_changes_check_read_only_and_the_combined_config():
    v = params.defaults()
    assert params.check_change(v, {"top_k": 20, "mode": "localization"}) is None
    assert params.check_change(v, {"weights": "/x.pth"}) == (
        "weights is read-only: set it at start-up (--ros-args -p weights:=...)"
    )
    assert params.check_change(v, {"mode": "slam"}) == (
        "mode='slam' must be one of mapping, localization"
    )


def test_read_params_file_fills_defaults_and_checks(tmp_path):
    from pair_vpr_ros.errors import ConfigError
    from pair_vpr_ros.params.configs import detector_config
    from pair_vpr_ros.params.file import read_params_file

    good = tmp_path / "p.yaml"
    good.write_text("vpr_node:\n  ros__parameters:\n    top_k: 3\n    exclude_recent_s: 12\n")
    values = read_params_file(good)
    assert values["top_k"] == 3 and values["exclude_recent_s"] == 12.0
    assert values["score_threshold"] == params.defaults()["score_threshold"]
    assert detector_config(values).top_k == 3
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    top_k: -4\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: top_k=-4 is out of range \[0, 1000\]"):
        read_params_file(bad)
    bad.write_text("other_node:\n  ros__parameters: {}\n")
    with pytest.raises(ConfigError, match="has no '/\\*\\*:' or 'vpr_node:' section"):
        read_params_file(bad)
    assert (
        read_params_file(Path(__file__).parents[2] / "config/vpr_node.yaml") == params.defaults()
    )


def test_an_old_file_with_the_degree_floor_still_works(tmp_path):
    """`pose_floor_rotation_deg` was the rotation floor itself (0.2); it is now a lower bound
    of the per-camera systematic term `pose_systematic_px` (default 0), so an old file keeps
    at least its floor; a camera with `pose_systematic_px` set gets its pixels' angle."""
    from pair_vpr_ros.geometry.camera import camera_from_params
    from pair_vpr_ros.geometry.covariance import systematic_rotation_deg
    from pair_vpr_ros.params.configs import geometry_config
    from pair_vpr_ros.params.file import read_params_file

    old = tmp_path / "old.yaml"
    old.write_text("/**:\n  ros__parameters:\n    pose_floor_rotation_deg: 0.2\n")
    pose = geometry_config(read_params_file(old)).pose
    assert (pose.floor_rotation_deg, pose.systematic_px, pose.floor_px) == (0.2, 0.0, 0.25)
    wide = camera_from_params(1242, 375, 718.0, 718.0, 621.0, 187.0)  # 1.8 px: 0.14 deg
    assert systematic_rotation_deg(pose, wide, wide) == 0.2
    assert systematic_rotation_deg(type(pose)(), wide) == 0.0
    rolling = type(pose)(systematic_px=1.8)
    assert systematic_rotation_deg(rolling, wide) == pytest.approx(0.1436, abs=1e-4)
