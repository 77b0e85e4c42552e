"""The `ros2` command lines our docs show, carried out through rclpy the way ros2cli does.

ros2cli is not on PyPI. `ros2 service call NAME TYPE YAML` fills the request from YAML and calls
the service; `ros2 param set NODE NAME VALUE` reads VALUE as YAML (true -> bool, 20 -> int,
text -> string) and calls NODE/set_parameters; `ros2 param describe` calls
NODE/describe_parameters. A `Graph` runs the node under test and a peer node in one executor
thread; the peer does what the CLI would.
"""

from __future__ import annotations

import importlib
import re
import shlex
import threading
import time
from typing import Any

import rclpy
import yaml
from ament_index_python.packages import get_package_prefix
from rcl_interfaces.srv import DescribeParameters, SetParameters
from rclpy.executors import MultiThreadedExecutor
from rclpy.parameter import Parameter

PKG_PREFIX = re.compile(r"\$\(ros2 pkg prefix (\w+)\)")


def wait_for(condition, timeout: float = 60.0) -> None:
    """Poll `condition` until true; generous: discovery is slow on busy cores."""
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.02)


def commands(block: str) -> list[list[str]]:
    """The shell commands of a code block, split as bash would (continuations joined, comments
    dropped, `$(ros2 pkg prefix PKG)` replaced by the package's ament prefix)."""
    joined = block.replace("\\\n", " ")
    out = []
    for line in joined.splitlines():
        line = PKG_PREFIX.sub(lambda m: get_package_prefix(m.group(1)), line)
        words = shlex.split(line, comments=True)
        if words:
            out.append(words)
    return out


def interface(type_name: str) -> Any:
    """`std_srvs/srv/SetBool` -> the class (as ros2cli's get_service / get_message do)."""
    package, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def parameter_value(name: str, text: str) -> Parameter:
    """What `ros2 param set NODE name TEXT` sends (ros2param reads TEXT as YAML)."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        value = text
    if not isinstance(value, bool | int | float | str | list):
        value = text
    return Parameter(name, value=value)


class Graph:
    """``node`` plus a peer that calls its services, both spun in one background executor."""

    def __init__(self, node) -> None:
        self.node = node
        self.peer = rclpy.create_node("ros2cli_peer")
        self.executor = MultiThreadedExecutor(num_threads=4)
        for n in (node, self.peer):
            self.executor.add_node(n)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def call(self, service: str, srv_type: Any, request: Any, timeout: float = 20.0) -> Any:
        client = self.peer.create_client(srv_type, service)
        try:
            assert client.wait_for_service(timeout_sec=10.0), f"no service {service}"
            future = client.call_async(request)
            wait_for(future.done, timeout)
            return future.result()
        finally:
            self.peer.destroy_client(client)

    def service_call(self, service: str, type_name: str, values: str = "{}") -> Any:
        """`ros2 service call SERVICE TYPE VALUES` (flat requests: fields set from the YAML)."""
        srv_type = interface(type_name)
        request = srv_type.Request()
        for key, value in (yaml.safe_load(values) or {}).items():
            assert hasattr(request, key), f"{type_name} request has no field {key!r}"
            setattr(request, key, value)
        return self.call(service, srv_type, request)

    def param_set(self, node: str, name: str, text: str) -> Any:
        """`ros2 param set NODE NAME TEXT` -> the SetParametersResult."""
        request = SetParameters.Request(
            parameters=[parameter_value(name, text).to_parameter_msg()]
        )
        return self.call(f"{node}/set_parameters", SetParameters, request).results[0]

    def param_describe(self, node: str, names: list[str]) -> list[Any]:
        """`ros2 param describe NODE NAMES...` -> ParameterDescriptors."""
        reply = self.call(f"{node}/describe_parameters", DescribeParameters,
                          DescribeParameters.Request(names=names))  # fmt: skip
        return list(reply.descriptors)

    def topics(self, node: str = "vpr_node") -> tuple[dict[str, list[str]], dict[str, list[str]]]:
        """({topic: types} published, {topic: types} subscribed) by ``node``, as the graph
        shows them (`ros2 node info`)."""
        wait_for(lambda: node in self.peer.get_node_names())
        pubs = self.peer.get_publisher_names_and_types_by_node(node, "/")
        subs = self.peer.get_subscriber_names_and_types_by_node(node, "/")
        return dict(pubs), dict(subs)

    def services(
        self, node: str = "vpr_node", expect: tuple[str, ...] = ()
    ) -> dict[str, list[str]]:
        """{service: types} of ``node`` once the services ``expect`` are discovered (a node's
        name is discovered before its services)."""

        def found() -> dict[str, list[str]]:
            return dict(self.peer.get_service_names_and_types_by_node(node, "/"))

        wait_for(lambda: node in self.peer.get_node_names() and set(expect) <= set(found()))
        return found()

    def close(self) -> None:
        self.executor.shutdown()
        self.thread.join(5.0)
        self.peer.destroy_node()
