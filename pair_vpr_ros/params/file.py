"""Parameter files: reading one (a key given twice refused), checking `--params-file` before rcl
does, and rendering one from a table (`config/*.yaml`)."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path
from typing import Any

import yaml

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.params.check import check_value
from pair_vpr_ros.params.rig import camera_sections
from pair_vpr_ros.params.table import PARAMS, ParamSpec, Value

INSTALLED_CONFIG = "$(ros2 pkg prefix pair_vpr_ros)/share/pair_vpr_ros/config/vpr_node.yaml"


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
        try:
            cameras = camera_sections(given) if "cameras" in specs else {}  # vpr_node's rig
        except ConfigError as err:
            raise ConfigError(f"parameter file {path}: {err}") from err
        for name, value in given.items():
            if name in cameras:  # a rig camera's own parameters: the node declares them
                continue
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
    table: tuple[ParamSpec, ...] = PARAMS,
    header: tuple[str, ...] = VPR_NODE_HEADER,
    values: dict[str, Value] | None = None,
) -> str:
    """A parameter file (`config/vpr_node.yaml` by default): every parameter of `table` with its
    default (or its entry in `values`), its description as a comment, after the comment lines
    `header`."""
    lines = [*header, "/**:", "  ros__parameters:"]
    values = values or {}
    for p in table:
        bounds = f" [{p.low}, {p.high}]" if p.low is not None else ""
        flag = " (read-only)" if p.read_only else ""
        text = f"{p.description}{bounds}{flag}"
        lines += textwrap.wrap(text, 95, initial_indent="    # ", subsequent_indent="    #   ")
        lines.append(f"    {p.name}: {_yaml_scalar(values.get(p.name, p.default))}")
    return "\n".join(lines) + "\n"
