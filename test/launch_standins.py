"""Small stand-ins for `launch` / `launch_ros` (not on PyPI), enough to run a launch file's
`generate_launch_description()` and turn its `Node` actions into the command lines launch_ros
would start: package, executable and the `--ros-args` it passes.

Only what our launch files use is modelled: `LaunchDescription`, `DeclareLaunchArgument`,
`LaunchConfiguration` (also `.perform(context)`), `OpaqueFunction`, `Shutdown` (as a node's
`on_exit`), `launch_ros.actions.Node` (parameters given as file paths or dicts of strings,
numbers or lists, remappings as pairs) and `launch_ros.parameter_descriptions.ParameterValue`
(a value of a given type: launch_ros passes a plain string value on as YAML, so "7" would be a
number; `value_type=str` keeps it text). Anything else fails loudly, so a launch file that grows
past this model fails its test instead of passing unchecked.
"""

from __future__ import annotations

import importlib.util
import json
import sys
import types
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


class LaunchArgumentError(Exception):
    """A required launch argument was not given (launch refuses to start then too)."""


@dataclass
class LaunchContext:
    launch_configurations: dict[str, str]


@dataclass
class LaunchConfiguration:
    variable_name: str

    def perform(self, context: LaunchContext) -> str:
        try:
            return context.launch_configurations[self.variable_name]
        except KeyError:
            raise LaunchArgumentError(
                f"launch configuration '{self.variable_name}' does not exist"
            ) from None


@dataclass
class DeclareLaunchArgument:
    name: str
    default_value: Any = None
    description: str = ""


@dataclass
class OpaqueFunction:
    function: Any
    args: list = field(default_factory=list)
    kwargs: dict = field(default_factory=dict)


@dataclass
class Node:
    package: str
    executable: str
    name: str | None = None
    namespace: str | None = None
    output: str = "log"
    parameters: list = field(default_factory=list)
    remappings: list = field(default_factory=list)
    arguments: list = field(default_factory=list)
    on_exit: Any = None  # an action run when the process ends (Shutdown is modelled)


@dataclass
class Shutdown:
    reason: str = ""


@dataclass
class LaunchDescription:
    entities: list


@dataclass
class ParameterValue:
    value: Any
    value_type: Any = None


class Text(str):
    """A parameter value launch_ros passes on as text (`ParameterValue(..., value_type=str)`)."""


def modules() -> dict[str, types.ModuleType]:
    """The stand-in modules, to put into `sys.modules` (e.g. with monkeypatch.setitem)."""
    made = {}
    for name, members in {
        "launch": {"LaunchDescription": LaunchDescription, "LaunchContext": LaunchContext},
        "launch.actions": {
            "DeclareLaunchArgument": DeclareLaunchArgument,
            "OpaqueFunction": OpaqueFunction,
            "Shutdown": Shutdown,
        },
        "launch.substitutions": {"LaunchConfiguration": LaunchConfiguration},
        "launch_ros": {},
        "launch_ros.actions": {"Node": Node},
        "launch_ros.parameter_descriptions": {"ParameterValue": ParameterValue},
    }.items():
        module = types.ModuleType(name)
        module.__dict__.update(members)
        made[name] = module
    made["launch"].actions = made["launch.actions"]
    made["launch"].substitutions = made["launch.substitutions"]
    made["launch_ros"].actions = made["launch_ros.actions"]
    made["launch_ros"].parameter_descriptions = made["launch_ros.parameter_descriptions"]
    return made


def installed(monkeypatch) -> None:
    """Put the stand-ins into sys.modules for one test."""
    for name, module in modules().items():
        monkeypatch.setitem(sys.modules, name, module)


def describe(path: Path) -> LaunchDescription:
    """Import the launch file at ``path`` (stand-ins must be in sys.modules) and run it."""
    name = "launch_file_" + path.stem.replace(".", "_")
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    assert isinstance(description, LaunchDescription), type(description)
    return description


def declared(description: LaunchDescription) -> dict[str, DeclareLaunchArgument]:
    return {e.name: e for e in description.entities if isinstance(e, DeclareLaunchArgument)}


def _text(value: Any, context: LaunchContext) -> Any:
    if isinstance(value, ParameterValue):
        assert value.value_type in (None, str), f"not modelled: {value!r}"
        inner = _text(value.value, context)
        return Text(inner) if value.value_type is str else inner
    if isinstance(value, str | list | float | int):  # a plain value (a list: a ROS array)
        return value
    assert isinstance(value, LaunchConfiguration), f"not modelled: {value!r}"
    return value.perform(context)


def launch(description: LaunchDescription, arguments: dict[str, str]) -> list[Node]:
    """The nodes ``ros2 launch ... name:=value`` would start, every substitution performed."""
    context = LaunchContext(dict(arguments))
    pending = list(description.entities)
    started = []
    while pending:
        entity = pending.pop(0)
        if isinstance(entity, DeclareLaunchArgument):
            if entity.name not in context.launch_configurations:
                if entity.default_value is None:
                    raise LaunchArgumentError(f"required launch argument '{entity.name}'")
                value = _text(entity.default_value, context)
                context.launch_configurations[entity.name] = value
        elif isinstance(entity, OpaqueFunction):
            pending[:0] = entity.function(context, *entity.args, **entity.kwargs) or []
        elif isinstance(entity, Node):
            started.append(_performed(entity, context))
        else:
            raise AssertionError(f"a launch entity these stand-ins do not model: {entity!r}")
    return started


def _performed(node: Node, context: LaunchContext) -> Node:
    parameters = [
        {k: _text(v, context) for k, v in p.items()} if isinstance(p, dict) else _text(p, context)
        for p in node.parameters
    ]
    remappings = [(_text(a, context), _text(b, context)) for a, b in node.remappings]
    assert node.on_exit is None or isinstance(node.on_exit, Shutdown), f"not modelled: {node!r}"
    return Node(
        node.package, node.executable, node.name, node.namespace, node.output,
        parameters, remappings, list(node.arguments), node.on_exit,
    )  # fmt: skip


def _arg(value: Any) -> str:
    """A parameter value as launch_ros writes it on the command line (YAML: text quoted)."""
    if isinstance(value, Text):
        return json.dumps(str(value))
    if isinstance(value, list):
        return "[" + ", ".join(str(v) for v in value) + "]"
    return str(value)


def ros_args(node: Node) -> list[str]:
    """The `--ros-args ...` launch_ros passes to a launched ``node`` (parameters in order)."""
    out = ["--ros-args"]
    if node.name:
        out += ["-r", f"__node:={node.name}"]
    if node.namespace:
        out += ["-r", f"__ns:={node.namespace}"]
    for entry in node.parameters:
        if isinstance(entry, dict):
            out += [a for key, value in entry.items() for a in ("-p", f"{key}:={_arg(value)}")]
        else:
            out += ["--params-file", entry]
    return out + [a for source, target in node.remappings for a in ("-r", f"{source}:={target}")]
