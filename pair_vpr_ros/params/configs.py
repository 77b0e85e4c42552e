"""The parameters of `vpr_node`, ROS-free: one table, validation, and the detector config.

`ros/parameters.py` declares every entry of `PARAMS` with a `ParameterDescriptor` built from it,
and `config/vpr_node.yaml` mirrors the table (`yaml_text()` renders it; a test keeps them equal).
`read_only` parameters take effect at start-up only; the others can change at run time
(`ros2 param set /vpr_node top_k 20`), and a refused change comes back with the reason.
The table lives in `table`, value checks in `check`, parameter files in `file`; the package
(`from pair_vpr_ros import params`) exports every public name.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.geometry.relpose import PoseConfig
from pair_vpr_ros.loops.detector import DetectorConfig, preset
from pair_vpr_ros.params.check import check_value
from pair_vpr_ros.params.table import DETECTOR_PARAMS, PARAMS, SPECS, Value
from pair_vpr_ros.place_map.index import IndexConfig


def defaults() -> dict[str, Value]:
    return {p.name: p.default for p in PARAMS}


def geometry_config(values: Mapping[str, Any]) -> GeometryConfig:
    """The pipeline's `GeometryConfig` of a full parameter set."""
    return GeometryConfig(
        relative_pose=values["relative_pose"],
        features=values["features"],
        max_features=values["max_features"],
        compact_features=values["feature_storage"] == "compact",
        pose=PoseConfig(
            depth_sigma_a=values["depth_sigma_a"],
            depth_sigma_b=values["depth_sigma_b"],
            max_depth_m=values["max_depth"],
            floor_px=values["pose_floor_px"],
            systematic_px=values["pose_systematic_px"],
            floor_rotation_deg=values["pose_floor_rotation_deg"],
            floor_translation_m=values["pose_floor_translation_m"],
            floor_translation_rel=values["pose_floor_translation_rel"],
        ),
    )


def index_config(values: Mapping[str, Any]) -> IndexConfig:
    """The place map's `IndexConfig` of a full parameter set (kind + the milvus settings)."""
    codec = values.get("dense_codec", IndexConfig.dense_codec)
    if values["index"] != "milvus":
        return IndexConfig(kind=values["index"], dense_codec=codec)
    names = ("milvus_uri", "milvus_collection", "milvus_index", "milvus_token_env")
    names += ("milvus_consistency",)
    return IndexConfig(kind="milvus", dense_codec=codec, **{name: values[name] for name in names})


def detector_config(values: Mapping[str, Any]) -> DetectorConfig:
    """The `DetectorConfig` of a full parameter set: the preset, then explicit overrides."""
    overrides = {k: values[k] for k in DETECTOR_PARAMS if k != "preset"}
    if overrides["top_k"] == 0:
        del overrides["top_k"]
    if overrides["min_frame_interval"] < 0:
        del overrides["min_frame_interval"]
    return preset(values["preset"], **overrides)


def check_change(current: Mapping[str, Any], changes: Mapping[str, Any]) -> str | None:
    """Why applying `changes` to the parameter set `current` is refused (None: accepted)."""
    for name, value in changes.items():
        reason = check_value(name, value)
        if reason is None and SPECS[name].read_only:
            reason = f"{name} is read-only: set it at start-up (--ros-args -p {name}:=...)"
        if reason is not None:
            return reason
    if any(name in DETECTOR_PARAMS for name in changes):
        try:
            detector_config({**current, **changes})
        except ConfigError as err:
            return str(err)
    return None
