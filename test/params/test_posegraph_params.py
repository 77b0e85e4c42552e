"""posegraph_node's parameter table: mirrored in config/posegraph_node.yaml, one entry per
PoseGraphConfig field with the same default, and read by pairvpr-posegraph --params-file."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.params import posegraph as params
from pair_vpr_ros.params.check import check_value
from pair_vpr_ros.params.file import read_params_file
from pair_vpr_ros.posegraph.config import PoseGraphConfig

CONFIG = Path(__file__).parents[2] / "config" / "posegraph_node.yaml"


def test_config_file_mirrors_the_table():
    assert CONFIG.read_text() == params.posegraph_yaml_text()


def test_every_graph_setting_is_a_parameter_with_the_same_default():
    defaults = PoseGraphConfig()
    for field in dataclasses.fields(PoseGraphConfig):
        assert params.SPECS[field.name].default == getattr(defaults, field.name), field.name
        assert params.SPECS[field.name].read_only
    assert params.posegraph_config(params.defaults()) == defaults


def test_parameter_file_round_trip(tmp_path):
    assert read_params_file(CONFIG, params.NODE_NAME, params.PARAMS) == params.defaults()
    path = tmp_path / "p.yaml"
    path.write_text(
        "posegraph_node:\n  ros__parameters:\n"
        "    camera_to_base: [0, 0, 1.6, -0.5, 0.5, -0.5, 0.5]\n"
        "    loop_kernel: huber\n    node_spacing_m: 2\n"
    )
    config = params.posegraph_config(read_params_file(path, params.NODE_NAME, params.PARAMS))
    assert config.camera_to_base == (0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5)
    assert (config.loop_kernel, config.node_spacing_m) == ("huber", 2.0)


@pytest.mark.parametrize(
    ("name", "value", "reason"),
    [
        ("camera_to_base", [0.0] * 6, "camera_to_base must be a list of 7 numbers, got [0.0, 0.0"),
        ("camera_to_base", [0, 0, 0, 0, 0, 0, True], "must be a list of 7 numbers"),
        ("camera_to_base", [float("nan")] * 7, "camera_to_base must hold finite numbers"),
        ("loop_kernel", "l2", "loop_kernel='l2' must be one of cauchy, huber, none"),
        ("node_spacing_m", 0.0, "node_spacing_m=0.0 is out of range [0.01, 1000.0]"),
        ("loop_iterations", 1.5, "loop_iterations must be an integer, got 1.5"),
        ("prior_map_dirs", "/a", "prior_map_dirs must be a list of non-empty strings, got '/a'"),
        ("prior_map_dirs", ["/maps/a", ""], "prior_map_dirs must be a list of non-empty strings"),
    ],
)
def test_bad_values(name, value, reason):
    assert reason in check_value(name, value, params.SPECS)


def test_bad_file_names_the_node(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("vpr_node:\n  ros__parameters:\n    top_k: 3\n")
    with pytest.raises(ConfigError, match="no '/\\*\\*:' or 'posegraph_node:' section"):
        read_params_file(path, params.NODE_NAME, params.PARAMS)
