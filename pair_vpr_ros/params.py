"""The parameters of `vpr_node`, ROS-free: one table, validation, and the detector config.

`node.py` declares every entry of `PARAMS` with a `ParameterDescriptor` built from it, and
`config/vpr_node.yaml` mirrors the table (`yaml_text()` renders it; a test keeps them equal).
`read_only` parameters take effect at start-up only; the others can change at run time
(`ros2 param set /vpr_node top_k 20`), and a refused change comes back with the reason.
"""

from __future__ import annotations

import argparse
import math
import os
import textwrap
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from pair_vpr_ros.detector import DetectorConfig, preset
from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.fleet.params import FLEET_PARAMS
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.geometry.relpose import PoseConfig
from pair_vpr_ros.identity import DEFAULT_ROBOT, RULE, name_problem
from pair_vpr_ros.imaging import MAX_PIXELS
from pair_vpr_ros.model.config import PATCH
from pair_vpr_ros.place_map.index import IndexConfig

# A tuple default: a fixed-size double array, or (ParamSpec.strings) a string array of any size.
Value = bool | int | float | str | tuple[float, ...] | tuple[str, ...]
INSTALLED_CONFIG = "$(ros2 pkg prefix pair_vpr_ros)/share/pair_vpr_ros/config/vpr_node.yaml"
RANDOM_TINY = "random-tiny"  # test-only weights value: a tiny random network (finds nothing real)
TYPE_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: its default fixes the ROS type; `low`/`high` bound numbers."""

    name: str
    default: Value
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = False
    strings: bool = False  # a string array (default ()): ROS STRING_ARRAY


def _p(name: str, default: Value, description: str, *bounds: float, **kw: Any) -> ParamSpec:
    low, high = bounds if bounds else (None, None)
    return ParamSpec(name, default, description, low, high, **kw)


RO = dict(read_only=True)
PARAMS: tuple[ParamSpec, ...] = (
    # ---- model (start-up only)
    _p("weights", "", "Pair-VPR checkpoint (.pth), e.g. /path/pairvpr-vitB.pth; '' = "
       "$PAIRVPR_WEIGHTS, else the one .pth in $XDG_DATA_HOME/pair_vpr_ros/ (default "
       f"~/.local/share/pair_vpr_ros/); '{RANDOM_TINY}' builds a tiny random network (tests only)",
       **RO),
    _p("device", "cpu", "torch device: cpu, cuda, cuda:1, auto (cuda when there is one)", **RO),
    _p("precision", "fp32", "fp32; int8 (dynamic quantization, CPU only); bf16 (autocast, CPU "
       "or GPU); fp16 (autocast, GPU only)", choices=("fp32", "int8", "bf16", "fp16"), **RO),
    _p("backend", "torch", "inference runtime: torch (the reference); openvino (CPU only, "
       "optional package: pip install 'pair_vpr_ros[openvino]'; precision fp32, bf16 or int8 "
       "= static int8 calibrated at the first start, see openvino_cache_dir)",
       choices=("torch", "openvino"), **RO),
    _p("openvino_cache_dir", "auto", "backend openvino: folder that keeps the converted (int8: "
       "quantized) model, so later starts skip export and calibration; auto = "
       "$XDG_CACHE_HOME/pair_vpr_ros/openvino (default ~/.cache/pair_vpr_ros/openvino); '' = no "
       "cache", **RO),
    _p("image_size", 0, "network input side in pixels, a multiple of 14; 0: the checkpoint's",
       0, 1022, **RO),
    _p("index", "flat", "map index: flat (exact), ivf (exact below 25,000 keyframes, then k-means "
       "lists: large maps), hnsw (graph) or milvus (a Milvus collection: milvus_uri; optional "
       "package: pip install 'pair_vpr_ros[milvus]')",
       choices=("flat", "hnsw", "ivf", "milvus"), **RO),
    _p("milvus_uri", "", "index milvus: a milvus-lite file (path ending in .db, created if "
       "missing) or a Milvus server address (http://host:19530)", **RO),
    _p("milvus_collection", "pairvpr_keyframes", "index milvus: the collection (maps of one "
       "model may share it, see docs/milvus.md)", **RO),
    _p("milvus_index", "IVF_FLAT", "index milvus: the collection's vector index (made when the "
       "collection is created; docs/milvus.md compares them)",
       choices=("IVF_FLAT", "HNSW", "FLAT"), **RO),
    _p("milvus_token_env", "PAIRVPR_MILVUS_TOKEN", "index milvus: name of the environment "
       "variable that holds the server token (the token is never a parameter, never logged)",
       **RO),
    # ---- inputs (start-up only)
    _p("image_topic", "image", "sensor_msgs/Image input topic ('' = none)", **RO),
    _p("compressed_image_topic", "", "sensor_msgs/CompressedImage input topic ('' = none)", **RO),
    _p("pose_topic", "", "pose input topic attached to keyframes ('' = none)", **RO),
    _p("pose_type", "odometry", "message type of pose_topic",
       choices=("odometry", "pose_stamped", "pose_with_covariance_stamped"), **RO),
    _p("pose_buffer_size", 2000, "poses kept for matching frames by stamp", 10, 1000000, **RO),
    _p("depth_topic", "", "sensor_msgs/Image depth aligned with the colour image (16UC1 mm or "
       "32FC1 m) for metric relative poses ('' = none: monocular)", **RO),
    _p("camera_info_topic", "", "sensor_msgs/CameraInfo of the colour camera: intrinsics for "
       "relative poses ('' = none: use the camera_* parameters)", **RO),
    _p("depth_tolerance", 0.02, "largest stamp gap (s) between an image and its depth image",
       0.0, 1.0, **RO),
    _p("camera_fx", 0.0, "fallback intrinsics when no camera_info arrives: focal length x in "
       "pixels of the incoming images (0 = none: no relative poses without camera_info)",
       0.0, 1.0e6, **RO),
    _p("camera_fy", 0.0, "fallback focal length y, px (0 = camera_fx)", 0.0, 1.0e6, **RO),
    _p("camera_cx", -1.0, "fallback principal point x, px (-1 = image centre)", -1.0, 1.0e6,
       **RO),
    _p("camera_cy", -1.0, "fallback principal point y, px (-1 = image centre)", -1.0, 1.0e6,
       **RO),
    _p("camera_distortion_model", "none", "fallback distortion model",
       choices=("none", "plumb_bob", "rational_polynomial", "equidistant"), **RO),
    _p("camera_distortion", "", "fallback distortion coefficients, comma-separated (plumb_bob: "
       "k1, k2, t1, t2, k3; equidistant: k1, k2, k3, k4)", **RO),
    _p("relative_pose", True, "compute T_match_query (+ covariance) for accepted loops: "
       "features of every keyframe are extracted and stored in the map", **RO),
    _p("features", "sift", "keypoints for relative poses: sift (accurate) or orb (cheaper)",
       choices=("sift", "orb"), **RO),
    _p("max_features", 1000, "keypoints per keyframe at most", 50, 100000, **RO),
    _p("depth_sigma_a", 0.0012, "depth noise sigma_z = a + b z^2 (m): a; defaults from "
       "published Kinect noise studies (docs/real-cameras.md)", 0.0, 10.0, **RO),
    _p("depth_sigma_b", 0.0019, "depth noise: b (1/m); stereo: sigma_disparity / (f baseline)",
       1e-9, 10.0, **RO),
    _p("max_depth", 0.0, "depth beyond this (m) is not used for relative poses (0 = no limit)",
       0.0, 1.0e4, **RO),
    _p("pose_floor_rotation_deg", 0.2, "covariance floor of relative poses: rotation std per "
       "axis (deg) for errors no residual shows (calibration, timing; docs/real-cameras.md)",
       0.0, 90.0, **RO),
    _p("pose_floor_translation_m", 0.005, "covariance floor: translation std (m), plus ...",
       0.0, 100.0, **RO),
    _p("pose_floor_translation_rel", 0.01, "... this fraction of the translation's length",
       0.0, 10.0, **RO),
    _p("right_image_topic", "", "stereo: sensor_msgs/Image of the right camera, rectified like "
       "the left (image_topic); keyframe depth from StereoSGBM ('' = none)", **RO),
    _p("right_camera_info_topic", "", "stereo: sensor_msgs/CameraInfo of the right camera "
       "(its P gives the baseline)", **RO),
    _p("qos", "sensor_data", "input QoS: sensor_data (best effort, hears every publisher) or "
       "reliable (hears reliable publishers only)", choices=("sensor_data", "reliable"), **RO),
    _p("queue_size", 4, "frames waiting for the worker; when full the oldest is dropped",
       1, 1000, **RO),
    _p("diagnostics_period", 1.0, "seconds between /diagnostics messages", 0.1, 60.0, **RO),
    _p("autosave_period", 0.0, "seconds between saves of a changed map to map_dir (0 = off)",
       0.0, 86400.0, **RO),
    _p("load_map_on_start", False, "load the map in map_dir at start-up (empty if none yet)",
       **RO),
    # ---- identity and prior maps (start-up only; docs/fleet.md)
    _p("robot_id", "", "robot of every keyframe and loop ('' = the node's namespace without "
       f"slashes, else '{DEFAULT_ROBOT}'); {RULE}", **RO),
    _p("session_id", "", "session of every keyframe and loop ('' = the start time, UTC, "
       f"YYYYMMDDTHHMMSSZ); {RULE}; must not name a session of this robot in a prior map",
       **RO),
    _p("prior_map_dirs", (), "saved place maps loaded read-only at start-up and searched with "
       "the live map (e.g. earlier sessions or other robots); never written", strings=True,
       **RO),
    # ---- run time
    _p("save_on_shutdown", False, "save the map to map_dir when the node stops"),
    _p("map_dir", "", "map folder of the save_map / load_map / build_map services"),
    _p("build_source", "", "build_map input: a rosbag (folder, .mcap, .db3, .bag) or an image "
       "folder (sorted by name)"),
    _p("build_image_topic", "", "image topic of a build_source bag ('' = its only one)"),
    _p("build_image_period", 1.0, "seconds between the synthetic stamps of folder images",
       0.001, 3600.0),
    _p("max_image_pixels", MAX_PIXELS, "images larger than this (width * height) are skipped "
       "before decoding (a small PNG can claim 20000 x 20000)", 1, 1 << 30),
    _p("pose_tolerance", 0.2, "largest stamp gap (s) between a frame and its pose", 0.0, 60.0),
    _p("publish_rejected", False, "also publish rejected best candidates on the detail and json "
       "topics (accepted = 0)"),
    _p("marker_frame_id", "map", "frame of the loop-closure markers (the poses' frame)"),
    # ---- detector (run time)
    _p("mode", "mapping", "mapping: query, then add keyframes; localization: query only",
       choices=("mapping", "localization")),
    _p("preset", "speed", "detector preset (speed: top_k 10, min_frame_interval 0.2; "
       "performance: top_k 100, min_frame_interval 0)", choices=("speed", "performance")),
    _p("top_k", 0, "candidates re-ranked per keyframe (0 = the preset's)", 0, 1000),
    _p("rerank_budget_ms", 0.0, "latency budget of re-ranking per keyframe, ms: candidates are "
       "scored best-global first until the next step would overrun it (the global best always "
       "is); the record's 'scored' says how many. 0 = no budget: all top_k", 0.0, 600000.0),
    _p("score_threshold", 0.0, "accept when logit(q,c) + logit(c,q) >= this", -1.0e6, 1.0e6),
    _p("global_floor", -1.0, "skip re-ranking below this global similarity (-1 = off)",
       -1.0, 1.0),
    _p("min_frame_interval", -1.0, "skip frames closer than this (s) to the last encoded one "
       "(-1 = the preset's)", -1.0, 3600.0),
    _p("keyframe_max_similarity", 0.98, "a frame this similar to the last keyframe is skipped",
       -1.0, 1.0),
    _p("exclude_recent_s", 30.0, "never match keyframes stamped within this many seconds of the "
       "query, before or after it (a bag played again, a clock reset)", 0.0, 86400.0),
    _p("exclude_recent_keyframes", 10, "... nor among the newest this many", 0, 1000000),
    _p("temporal_consistency", 1, "accept after this many consecutive agreeing queries", 1, 100),
    _p("temporal_tolerance", 5, "agreeing: matched ids within this many keyframes", 0, 100000),
    _p("geometric_verification", False, "also require ORB + fundamental-matrix RANSAC inliers"),
    _p("min_inliers", 15, "inliers needed with geometric_verification", 0, 100000),
)  # fmt: skip

PARAMS += tuple(  # fleet exchange: all start-up only; a row may end with keyword arguments
    _p(*row[:-1], **RO, **row[-1]) if isinstance(row[-1], dict) else _p(*row, **RO)
    for row in FLEET_PARAMS
)
SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMS}
DETECTOR_PARAMS = (
    "mode",
    "preset",
    "top_k",
    "rerank_budget_ms",
    "score_threshold",
    "global_floor",
    "min_frame_interval",
    "keyframe_max_similarity",
    "exclude_recent_s",
    "exclude_recent_keyframes",
    "temporal_consistency",
    "temporal_tolerance",
    "geometric_verification",
    "min_inliers",
)


def defaults() -> dict[str, Value]:
    return {p.name: p.default for p in PARAMS}


def check_value(name: str, value: Any, specs: Mapping[str, ParamSpec] | None = None) -> str | None:
    """Why `value` is not valid for parameter `name` of `specs` (default: vpr_node's; None when
    it is valid)."""
    spec = (SPECS if specs is None else specs).get(name)
    if spec is None:
        return f"unknown parameter {name!r}"
    if spec.strings:
        return _check_strings(name, value)
    if isinstance(spec.default, tuple):
        return _check_array(name, value, len(spec.default))
    kind = type(spec.default)
    ok = isinstance(value, kind) and not (kind is not bool and isinstance(value, bool))
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        ok, value = True, float(value)
    if not ok:
        return f"{name} must be {TYPE_NAMES[kind]}, got {value!r}"
    if kind is float and not math.isfinite(value):
        return f"{name} must be a finite number, got {value!r}"
    if spec.low is not None and not spec.low <= value <= spec.high:
        return f"{name}={value!r} is out of range [{spec.low}, {spec.high}]"
    if spec.choices and value not in spec.choices:
        return f"{name}={value!r} must be one of {', '.join(spec.choices)}"
    if name == "image_size" and value % PATCH:
        return f"image_size={value} must be 0 or a multiple of {PATCH} (e.g. 224, 322)"
    if name in ("robot_id", "session_id") and value:
        return name_problem(name, value)
    if name == "camera_distortion":
        try:
            [float(x) for x in value.replace(",", " ").split()]
        except ValueError:
            return f"camera_distortion={value!r} must be comma-separated numbers"
    return None


def flag_type(name: str) -> Callable[[str], Value]:
    """An argparse type for a command-line flag that mirrors number parameter `name` (the
    replay's --rerank-budget-ms): parsed as the parameter's type and checked by `check_value`,
    so the flag and a parameter file refuse the same values with the same words."""
    kind = type(SPECS[name].default)

    def parse(text: str) -> Value:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{name} must be {TYPE_NAMES[kind]}, got {text!r}"
            ) from None
        reason = check_value(name, value)
        if reason is not None:
            raise argparse.ArgumentTypeError(reason)
        return value

    return parse


def flag_help(name: str) -> str:
    """The help text of a flag that mirrors parameter `name`: its description and range."""
    spec = SPECS[name]
    bounds = f" [{spec.low:g}, {spec.high:g}]" if spec.low is not None else ""
    return f"{spec.description}{bounds}".replace("%", "%%")


def _check_strings(name: str, value: Any) -> str | None:
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) and v for v in value):
        return f"{name} must be a list of non-empty strings, got {value!r}"
    return None


def _check_array(name: str, value: Any, size: int) -> str | None:
    numbers = isinstance(value, (list, tuple)) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
    )
    if not numbers or len(value) != size:
        return f"{name} must be a list of {size} numbers, got {value!r}"
    if not all(math.isfinite(v) for v in value):
        return f"{name} must hold finite numbers, got {value!r}"
    return None


def geometry_config(values: Mapping[str, Any]) -> GeometryConfig:
    """The pipeline's `GeometryConfig` of a full parameter set."""
    return GeometryConfig(
        relative_pose=values["relative_pose"],
        features=values["features"],
        max_features=values["max_features"],
        pose=PoseConfig(
            depth_sigma_a=values["depth_sigma_a"],
            depth_sigma_b=values["depth_sigma_b"],
            max_depth_m=values["max_depth"],
            floor_rotation_deg=values["pose_floor_rotation_deg"],
            floor_translation_m=values["pose_floor_translation_m"],
            floor_translation_rel=values["pose_floor_translation_rel"],
        ),
    )


def index_config(values: Mapping[str, Any]) -> IndexConfig:
    """The place map's `IndexConfig` of a full parameter set (kind + the milvus settings)."""
    if values["index"] != "milvus":
        return IndexConfig(kind=values["index"])
    names = ("milvus_uri", "milvus_collection", "milvus_index", "milvus_token_env")
    return IndexConfig(kind="milvus", **{name: values[name] for name in names})


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


class DuplicateKeyError(yaml.YAMLError):
    """A key given twice in one YAML mapping (PyYAML and rcl keep the last without a word)."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            if key in seen:
                raise DuplicateKeyError(
                    f"{key!r} is given twice (lines {seen[key]} and {line}): keep one (YAML "
                    "would use the last one without a word)"
                )
            seen[key] = line
        return super().construct_mapping(node, deep=deep)


def load_yaml(text: str) -> Any:
    """`yaml.safe_load` that raises DuplicateKeyError for a key given twice in one mapping."""
    return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass


def params_file_problem(args: list[str]) -> str | None:
    """Why a `--params-file` of the command line `args` cannot be read (None: all can). rcl
    would raise an RCLError traceback for a missing one."""
    for flag, path in zip(args, args[1:], strict=False):
        if flag != "--params-file":
            continue
        where = Path(path)
        if not where.is_file():
            what = "is a folder" if where.is_dir() else "does not exist"
            what += "" if where.is_absolute() else f" (relative to {Path.cwd()})"
            return (
                f"--params-file {path} {what}: give a parameter file, e.g. the installed one, "
                f"{INSTALLED_CONFIG}"
            )
        if not os.access(where, os.R_OK):
            return f"--params-file {path} cannot be read (permissions): give a readable file"
        try:
            load_yaml(where.read_bytes().decode("utf-8"))
        except DuplicateKeyError as err:
            return f"--params-file {path}: {err}"
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            pass  # rcl's parser reports these
    return None


def read_params_file(
    path: str | Path, node_name: str = "vpr_node", table: tuple[ParamSpec, ...] = PARAMS
) -> dict[str, Value]:
    """The full parameter set of a ROS 2 parameter file (`/**:` or `<node_name>:` with
    `ros__parameters`) for the parameters in `table`, defaults filled in and every value checked
    (ConfigError)."""
    path = Path(path)
    layout = f"see config/{node_name}.yaml: '/**:' or '{node_name}:', then 'ros__parameters:'"
    try:
        data = load_yaml(path.read_bytes().decode("utf-8"))
    except DuplicateKeyError as err:
        raise ConfigError(f"parameter file {path}: {err}") from err
    except UnicodeDecodeError as err:
        raise ConfigError(
            f"parameter file {path} is not a text (UTF-8) file ({err.reason} at byte "
            f"{err.start}): pass a YAML parameter file ({layout})"
        ) from err
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f"cannot read parameter file {path}: {err}") from err
    if data is None:
        raise ConfigError(f"parameter file {path} is empty ({layout})")
    if not isinstance(data, dict):
        raise ConfigError(
            f"parameter file {path} holds a {type(data).__name__} at the top level, not a "
            f"mapping of node names ({layout})"
        )
    sections = [v for k, v in data.items() if k in ("/**", node_name, f"/{node_name}")]
    if not sections or not all(isinstance(v, dict) and "ros__parameters" in v for v in sections):
        raise ConfigError(
            f"parameter file {path} has no '/**:' or '{node_name}:' section with "
            f"'ros__parameters:' ({layout})"
        )
    specs = {p.name: p for p in table}
    values = {p.name: p.default for p in table}
    for section in sections:
        given = section["ros__parameters"] or {}
        if not isinstance(given, dict):
            raise ConfigError(
                f"parameter file {path}: ros__parameters holds a {type(given).__name__}, not a "
                f"mapping of parameter names to values ({layout})"
            )
        for name, value in given.items():
            if name in specs and specs[name].strings and value is None:
                value = ()  # `name: []` in YAML (rcl reads it as unset: the default, empty)
            reason = check_value(name, value, specs)
            if reason is not None:
                raise ConfigError(f"parameter file {path}: {reason}")
            default = specs[name].default
            if specs[name].strings:
                value = tuple(value)
            elif isinstance(default, tuple):
                value = tuple(float(v) for v in value)
            values[name] = float(value) if isinstance(default, float) else value
    return values


def _yaml_scalar(value: Value) -> str:
    if isinstance(value, tuple):
        items = (f'"{v}"' if isinstance(v, str) else repr(float(v)) for v in value)
        return "[" + ", ".join(items) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


VPR_NODE_HEADER = (
    "# vpr_node parameters (defaults). Start with:",
    "#   ros2 run pair_vpr_ros vpr_node --ros-args --params-file config/vpr_node.yaml \\",
    "#       -p weights:=/path/pairvpr-vitB.pth",
    "# (read-only) = start-up only; the others can change with `ros2 param set`.",
)


def yaml_text(
    table: tuple[ParamSpec, ...] = PARAMS, header: tuple[str, ...] = VPR_NODE_HEADER
) -> str:
    """A parameter file (`config/vpr_node.yaml` by default): every parameter of `table` with its
    default, its description as a comment, after the comment lines `header`."""
    lines = [*header, "/**:", "  ros__parameters:"]
    for p in table:
        bounds = f" [{p.low}, {p.high}]" if p.low is not None else ""
        flag = " (read-only)" if p.read_only else ""
        text = f"{p.description}{bounds}{flag}"
        lines += textwrap.wrap(text, 95, initial_indent="    # ", subsequent_indent="    #   ")
        lines.append(f"    {p.name}: {_yaml_scalar(p.default)}")
    return "\n".join(lines) + "\n"
