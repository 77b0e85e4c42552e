"""Checks of parameter values against the table (`table`), and the command-line flags
that mirror a parameter; ROS-free."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Mapping
from typing import Any

from pair_vpr_ros.identity import name_problem
from pair_vpr_ros.model.config import PATCH
from pair_vpr_ros.params.table import SPECS, ParamSpec, Value

TYPE_NAMES = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
# Parameters that were replaced: what an old parameter file should say instead.
RETIRED = {
    "pose_floor_rotation_px": (
        ": replaced by pose_systematic_px (this camera's systematic error, default 0: the "
        "covariance now comes from the inliers and the model checks) and pose_floor_px (a lower "
        "bound on the pixel noise); see docs/real-cameras.md"
    )
}


def check_value(name: str, value: Any, specs: Mapping[str, ParamSpec] | None = None) -> str | None:
    """Why `value` is not valid for parameter `name` of `specs` (default: vpr_node's; None when
    it is valid)."""
    spec = (SPECS if specs is None else specs).get(name)
    if spec is None:
        return f"unknown parameter {name!r}{RETIRED.get(name, '')}"
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
    if name == "fleet_peers":  # robot ids, comma-separated
        peers = [p.strip() for p in value.split(",") if p.strip()]
        return next(filter(None, (name_problem("fleet_peers robot", p) for p in peers)), None)
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
