"""ROS parameter descriptors built from the ROS-free parameter tables (``params.ParamSpec``)."""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from rclpy.parameter import Parameter

from pair_vpr_ros.params import ParamSpec, Value


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
