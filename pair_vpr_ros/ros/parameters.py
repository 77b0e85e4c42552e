"""ROS parameter descriptors built from the ROS-free parameter tables (``params.ParamSpec``)."""

from __future__ import annotations

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor

from pair_vpr_ros.params import ParamSpec


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
