"""The node page (docs/node.md, once the README's ROS section), line by line, against a running
`vpr_node` (tiny random network).

Every command line in the section's code blocks is carried out: `ros2 run` / `vpr_node` /
`ros2 launch` start the node with the arguments shown (the launch file through stand-ins),
`ros2 service call` and `ros2 param set` go through rclpy as ros2cli sends them, in the
README's order. The outputs table and the inputs are checked against the ROS graph, and
`ros2 param describe` against the parameter table. Placeholder paths (/path/...) become real
files in tmp_path; any other command, or a placeholder this test does not know, fails it.
"""

from __future__ import annotations

import re
from pathlib import Path

import launch_standins as ls
import pytest
import rclpy
from ament_index_python.packages import get_package_prefix
from bag_fixtures import synthetic_images, write_rosbag2
from package_layout import PACKAGE, ROOT, console_scripts, install_prefix
from ros_cli import Graph, commands, parameter_value, wait_for

from pair_vpr_ros.messages import loop as lm
from pair_vpr_ros.messages.factor import FACTOR_TOPIC
from pair_vpr_ros.messages.loop_image import IMAGE_TOPIC
from pair_vpr_ros.params.table import PARAMS, RANDOM_TINY, SPECS
from pair_vpr_ros.ros.node import VprNode
from pair_vpr_ros.ros.outputs import MARKER_TOPIC

HEADING = "# The ROS 2 node `vpr_node`"
PAGE = ROOT / "docs" / "node.md"
NODE = "/vpr_node"
OUTPUT_TOPICS = (lm.PAIR_TOPIC, lm.DETAIL_TOPIC, lm.JSON_TOPIC, FACTOR_TOPIC, MARKER_TOPIC,
                 IMAGE_TOPIC)  # fmt: skip


def ros_section() -> str:
    text = PAGE.read_text()
    start = text.index(HEADING)
    end = text.find("\n## ", start + 1)
    return text[start:end]


def section_commands() -> list[list[str]]:
    blocks = re.findall(r"```bash\n(.*?)```", ros_section(), re.S)
    return [words for block in blocks for words in commands(block)]


@pytest.fixture
def env(tmp_path, monkeypatch):
    """An install prefix on AMENT_PREFIX_PATH (for `$(ros2 pkg prefix ...)` and the launch file),
    the launch stand-ins, an rclpy context, and the real paths for the README's placeholders."""
    prefix = install_prefix(tmp_path / "install" / PACKAGE)
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    monkeypatch.chdir(ROOT)  # "from the repository root"
    ls.installed(monkeypatch)
    bag = write_rosbag2(
        tmp_path / "bag",
        [(10.0 + i, rgb) for i, rgb in enumerate(synthetic_images(3, size=32))],
    )
    paths = {
        "/path/pairvpr-vitB.pth": RANDOM_TINY,
        "/path/to/map": str(tmp_path / "map"),
        "/path/to/bag_or_image_folder": str(bag),
    }
    rclpy.init()
    yield paths
    rclpy.try_shutdown()


def placeholders(words: list[str], paths: dict[str, str]) -> list[str]:
    out = []
    for word in words:
        for placeholder, real in paths.items():
            word = word.replace(placeholder, real)
        assert "/path/" not in word, f"a placeholder this test does not know: {word}"
        out.append(word)
    return out


def node_arguments(words: list[str]) -> list[str]:
    """The `--ros-args ...` a start line gives the node (`ros2 run`, console script, launch)."""
    if words[:2] == ["ros2", "run"]:
        assert words[2] == PACKAGE and words[4] == "--ros-args", words
        assert console_scripts()[words[3]] == "pair_vpr_ros.ros.entry:vpr_node"
        # colcon puts console scripts where `ros2 run` looks: lib/<package>/
        assert f"install_scripts=$base/lib/{PACKAGE}" in (ROOT / "setup.cfg").read_text()
        return words[4:]
    if words[0] == "vpr_node":
        assert console_scripts()["vpr_node"] == "pair_vpr_ros.ros.entry:vpr_node"
        return words[1:]
    assert words[:4] == ["ros2", "launch", PACKAGE, "vpr_node.launch.py"], words
    share = Path(get_package_prefix(PACKAGE)) / "share" / PACKAGE
    description = ls.describe(share / "launch" / words[3])
    arguments = dict(w.split(":=", 1) for w in words[4:])
    assert set(arguments) <= set(ls.declared(description)), arguments
    (node,) = ls.launch(description, arguments)
    assert node.executable == "vpr_node" and node.package == PACKAGE
    return ls.ros_args(node)


def start_lines() -> list[list[str]]:
    return [w for w in section_commands() if w[:2] in (["ros2", "run"], ["ros2", "launch"])
            or w[0] == "vpr_node"]  # fmt: skip


def start(words: list[str], paths: dict[str, str]) -> tuple[VprNode, Graph]:
    args = node_arguments(placeholders(words, paths))
    for i, word in enumerate(args):  # the parameter file must exist where the line says
        if word == "--params-file":
            assert Path(args[i + 1]).is_file(), args[i + 1]
    node = VprNode(cli_args=args, start_worker=False)
    return node, Graph(node)


def stop(node: VprNode, graph: Graph) -> None:
    graph.close()
    node.shutdown()
    node.destroy_node()


def test_every_command_line_is_one_this_test_checks(env):
    lines = section_commands()
    kinds = [" ".join(w[:3]) if w[0] == "ros2" else w[0] for w in lines]
    known = {"ros2 run pair_vpr_ros", "ros2 launch pair_vpr_ros", "vpr_node",
             "ros2 service call", "ros2 param set"}  # fmt: skip
    assert set(kinds) <= known, set(kinds) - known
    assert len(start_lines()) == 3 and kinds.count("ros2 service call") >= 6


@pytest.mark.parametrize("index", [0, 1, 2])
def test_start_line_starts_the_node_with_its_remappings(env, index):
    words = start_lines()[index]
    args = node_arguments(placeholders(words, env))
    remaps = dict(args[i + 1].split(":=") for i, w in enumerate(args) if w == "-r")
    remaps.pop("__node", None)
    node, graph = start(words, env)
    try:
        assert node.get_fully_qualified_name() == NODE
        assert node.get_parameter("weights").value == RANDOM_TINY
        image = SPECS["image_topic"].default
        expected_subs = {"/" + remaps.get(image, image).lstrip("/")}
        base = "/" + remaps.get(lm.PAIR_TOPIC, lm.PAIR_TOPIC).lstrip("/")  # all follow it
        expected_pubs = {base + t.removeprefix(lm.PAIR_TOPIC) for t in OUTPUT_TOPICS}
        wait_for(lambda: expected_pubs <= set(graph.topics()[0]))
        published, subscribed = graph.topics()
        assert set(subscribed) == expected_subs
        for source, target in remaps.items():  # the new name replaced one the node uses
            assert "/" + source not in published and "/" + source not in subscribed
            assert "/" + target.lstrip("/") in {**published, **subscribed}, (source, target)
    finally:
        stop(node, graph)


def test_service_and_param_lines_in_order(env, tmp_path):
    node, graph = start(start_lines()[0], env)
    try:
        calls = [w[3] for w in section_commands() if w[:3] == ["ros2", "service", "call"]]
        services = graph.services(expect=tuple(calls))
        for words in section_commands():
            words = placeholders(words, env)
            if words[:3] == ["ros2", "service", "call"]:
                name, type_name = words[3], words[4]
                assert services[name] == [type_name], name
                reply = graph.service_call(name, type_name, *words[5:])
                assert reply.success, (words, reply.message)
                if name.endswith("/build_map"):
                    assert node.maps.wait_build(60.0)
                    built = re.match(r"done: (\d+) keyframes from 3 images", node.maps.build_state)
                    assert built is not None, node.maps.build_state
                    keyframes = int(built[1])
            elif words[:3] == ["ros2", "param", "set"]:
                assert words[3] == NODE
                result = graph.param_set(words[3], words[4], words[5])
                assert result.successful, (words, result.reason)
                value = parameter_value(words[4], words[5]).value
                assert node.get_parameter(words[4]).value == value
        assert node.get_parameter("mode").value == "mapping"  # the last set_localization: false
        assert node.maps.size() == keyframes >= 1 and (tmp_path / "map").is_dir()
    finally:
        stop(node, graph)


def table_rows(text: str) -> list[tuple[str, str]]:
    """(`topic`, `type`) of the outputs table."""
    return re.findall(r"^\| `([^`]+)` \| `([^`]+)` \|", text, re.M)


def test_outputs_table_and_inputs_match_the_graph(env):
    words = next(w for w in start_lines() if w[0] == "vpr_node")  # no remappings
    section = ros_section()
    node, graph = start(words, env)
    try:
        rows = table_rows(section)
        assert len(rows) == 8
        expected = {"/" + topic.lstrip("/"): type_name for topic, type_name in rows}
        if node.outputs.typed is None:  # pair_vpr_ros_interfaces not built (PAIRVPR_INTERFACES)
            assert expected.pop("/loop_closure/typed") == "pair_vpr_ros_interfaces/LoopClosure"
        wait_for(lambda: set(expected) <= set(graph.topics()[0]))
        published, subscribed = graph.topics()
        for topic, type_name in expected.items():
            package, name = type_name.split("/")
            assert published[topic] == [f"{package}/msg/{name}"], topic
        image = re.search(r"\*\*Inputs\.\*\* `(\w+)` \(`(\w+)/(\w+)`", section)
        assert subscribed == {f"/{image[1]}": [f"{image[2]}/msg/{image[3]}"]}
        named = re.findall(r"`(\w+_topic)` \(`", section)
        assert named and all(n in SPECS for n in named), named
    finally:
        stop(node, graph)


def test_param_describe_and_the_run_time_parameters(env):
    section = ros_section()
    shown = re.search(r"`ros2 param describe (\S+) <name>`", section)
    assert shown is not None and shown[1] == NODE
    paragraph = section[section.index("**Parameters**") :].split("\n\n")[0]
    run_time = re.findall(r"`(\w+)`", paragraph.split("detector settings")[1])
    assert run_time and set(run_time) <= set(SPECS), run_time
    node, graph = start(start_lines()[0], env)
    try:
        names = [p.name for p in PARAMS]
        described = graph.param_describe(NODE, names)
        assert [d.name for d in described] == names
        for spec, d in zip(PARAMS, described, strict=True):
            assert (d.description, d.read_only) == (spec.description, spec.read_only), spec.name
        for name in run_time:
            text = str(SPECS[name].default).lower()
            result = graph.param_set(NODE, name, text)
            assert result.successful, (name, result.reason)
    finally:
        stop(node, graph)
