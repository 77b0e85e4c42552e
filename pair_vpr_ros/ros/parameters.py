"""ROS parameter descriptors built from the ROS-free parameter tables (``params.ParamSpec``), and
`vpr_node`'s parameter handling: declaring and checking the table at start-up, checking and
applying changes at run time (`ParameterHandling`, a mixin of `VprNode`)."""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from pair_vpr_ros import params
from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry.camera_notes import fallback_intrinsics_note
from pair_vpr_ros.params.table import ParamSpec, Value


def descriptor(spec: ParamSpec) -> ParameterDescriptor:
    """Description, read-only flag, choices and numeric range of one parameter."""
    d = ParameterDescriptor(description=spec.description, read_only=spec.read_only)
    if spec.choices:
        d.additional_constraints = "one of: " + ", ".join(spec.choices)
    if spec.low is not None and isinstance(spec.default, float):
        d.floating_point_range = [FloatingPointRange(from_value=spec.low, to_value=spec.high)]
    elif spec.low is not None:
        d.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=1)]
    return d


def declared_default(spec: ParamSpec) -> Any:
    """What `declare_parameter` takes as the default: the value, or for a string array the type
    (rclpy cannot type an empty list; it stays unset until given)."""
    return Parameter.Type.STRING_ARRAY if spec.strings else spec.default


def read_value(node: Node, spec: ParamSpec) -> Value:
    """The parameter's value (an unset string array: its default, ())."""
    if spec.strings:
        value = node.get_parameter_or(spec.name, Parameter(spec.name, value=[])).value
        return tuple(value or ())
    return node.get_parameter(spec.name).value


def declare_all(node: Node) -> dict[str, Value]:
    """Declare every parameter of `params.PARAMS` on `node`; their values, all checked
    (ConfigError naming every invalid one)."""
    for spec in params.PARAMS:
        node.declare_parameter(spec.name, declared_default(spec), descriptor(spec))
    v = {spec.name: read_value(node, spec) for spec in params.PARAMS}
    reasons = [r for name, value in v.items() if (r := params.check_value(name, value))]
    if reasons:
        raise ConfigError("invalid parameters: " + "; ".join(reasons))
    return v


class ParameterHandling:
    """Start-up warnings and run-time parameter changes of `VprNode` (it supplies `values`,
    `maps` and `_min_interval`)."""

    def _say_once(self, note: str) -> None:
        if note:
            self.get_logger().warning(note)

    def _warn_settings(self, v: dict) -> None:
        """Settings that are valid alone but do nothing together: say so at once."""
        self._demo_note: str | None = None
        self._say_once(fallback_intrinsics_note(v))
        if v["save_on_shutdown"] and not v["map_dir"]:
            self.get_logger().warning(
                "save_on_shutdown is true but map_dir is empty: nothing will be saved when the "
                "node stops; set map_dir (-p map_dir:=/path/to/map or ros2 param set)"
            )

    def _on_set_parameters(self, changed: list[Parameter]) -> SetParametersResult:
        reason = params.check_change(self.values, {p.name: p.value for p in changed})
        return SetParametersResult(successful=reason is None, reason=reason or "")

    def _after_set_parameters(self, changed: list[Parameter]) -> None:
        self.values = {**self.values, **{p.name: p.value for p in changed}}
        if any(p.name in ("save_on_shutdown", "map_dir") for p in changed):
            self._warn_settings(self.values)
        if any(p.name in params.DETECTOR_PARAMS for p in changed):
            config = params.detector_config(self.values)
            self.maps.set_config(config)
            self._min_interval = config.min_frame_interval
