"""Bad-input matrix, parameter files: whatever the file holds, `read_params_file` gives a
ConfigError naming the file and the problem (the replay's --params-file prints it as `error:`)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.params.file import params_file_problem, read_params_file


def section(body: str) -> str:
    return "/**:\n  ros__parameters:\n" + "".join(f"    {line}\n" for line in body.splitlines())


LAYOUT = "see config/vpr_node.yaml: '/**:' or 'vpr_node:', then 'ros__parameters:'"
CASES = {
    "empty": (b"", f"is empty ({LAYOUT})"),
    "comments only": (b"# nothing\n", "is empty"),
    "binary": (b"\x89PNG\r\n\x1a\n\x00\x00\xff", "is not a text (UTF-8) file (invalid start byte"),
    "utf-16": ("top_k: 3".encode("utf-16"), "is not a text (UTF-8) file"),
    "top-level list": (b"- 1\n- 2\n", "holds a list at the top level, not a mapping"),
    "top-level string": (b"hello\n", "holds a str at the top level, not a mapping"),
    "top-level number": (b"3.5\n", "holds a float at the top level"),
    "bad yaml": (b"/**: [unclosed\n", "cannot read parameter file"),
    "tab indent": (b"/**:\n\tros__parameters: {}\n", "cannot read parameter file"),
    "no section": (b"other_node:\n  ros__parameters: {}\n", "has no '/**:' or 'vpr_node:'"),
    "section is a number": (b"/**: 3\n", "has no '/**:' or 'vpr_node:' section"),
    "no ros__parameters": (b"/**:\n  top_k: 3\n", "has no '/**:' or 'vpr_node:' section"),
    "ros__parameters list": (
        b"/**:\n  ros__parameters:\n    - top_k\n    - 3\n",
        "ros__parameters holds a list, not a mapping of parameter names to values",
    ),
    "ros__parameters string": (
        b"vpr_node:\n  ros__parameters: top_k=3\n",
        "ros__parameters holds a str, not a mapping",
    ),
    "unknown name": (section("topk: 3").encode(), "unknown parameter 'topk'"),
    "number key": (section("3: 4").encode(), "unknown parameter 3"),
    "string for int": (section('top_k: "3"').encode(), "top_k must be an integer, got '3'"),
    "bool for int": (section("top_k: true").encode(), "top_k must be an integer, got True"),
    "float for int": (section("top_k: 3.5").encode(), "top_k must be an integer, got 3.5"),
    "list value": (section("top_k: [1, 2]").encode(), "top_k must be an integer, got [1, 2]"),
    "nan": (section("score_threshold: .nan").encode(), "score_threshold must be a finite number"),
    "inf": (section("exclude_recent_s: .inf").encode(), "exclude_recent_s must be a finite"),
    "out of range": (section("top_k: -4").encode(), "top_k=-4 is out of range [0, 1000]"),
    "negative margin": (
        section("sequence_margin: -2.0").encode(),
        "sequence_margin=-2.0 is out of range [0.0, 1000000.0]",
    ),
    "bad choice": (section("mode: slam").encode(), "mode='slam' must be one of mapping"),
    "backend typo": (
        section("backend: onnx").encode(),
        "backend='onnx' must be one of torch, openvino",
    ),
    "cache dir number": (
        section("openvino_cache_dir: 3").encode(),
        "openvino_cache_dir must be a string, got 3",
    ),
    "cache dir bool": (
        section("openvino_cache_dir: false").encode(),
        "openvino_cache_dir must be a string, got False",
    ),
    "image size": (section("image_size: 300").encode(), "image_size=300 must be 0 or a multiple"),
    "threads negative": (
        section("num_threads: -2").encode(),
        "num_threads=-2 is out of range [0, 1024]",
    ),
    "threads as a word": (  # auto is 0 in a parameter file (an integer parameter)
        section('num_threads: "auto"').encode(),
        "num_threads must be an integer, got 'auto'",
    ),
    "negative budget": (
        section("rerank_budget_ms: -1.0").encode(),
        "rerank_budget_ms=-1.0 is out of range [0.0, 600000.0]",
    ),
    "nan budget": (
        section("rerank_budget_ms: .nan").encode(),
        "rerank_budget_ms must be a finite",
    ),
    "string budget": (
        section('rerank_budget_ms: "250 ms"').encode(),
        "rerank_budget_ms must be a number, got '250 ms'",
    ),
    "negative global weight": (
        section("global_weight: -0.5").encode(),
        "global_weight=-0.5 is out of range [0.0, 10000.0]",
    ),
    "nan global weight": (
        section("global_weight: .nan").encode(),
        "global_weight must be a finite number",
    ),
    "string global weight": (
        section('global_weight: "high"').encode(),
        "global_weight must be a number, got 'high'",
    ),
    "key twice": (
        section("top_k: 3\nscore_threshold: 1.0\ntop_k: 20").encode(),
        "'top_k' is given twice (lines 3 and 5): keep one (YAML would use the last one without "
        "a word)",
    ),
    "section twice": (
        (section("top_k: 3") + section("top_k: 4")).encode(),
        "'/**' is given twice (lines 1 and 4): keep one",
    ),
    "negative systematic error": (
        section("pose_systematic_px: -1.0").encode(),
        "pose_systematic_px=-1.0 is out of range [0.0, 100.0]",
    ),
    "nan pixel floor": (
        section("pose_floor_px: .nan").encode(),
        "pose_floor_px must be a finite number, got nan",
    ),
    "string pixel floor": (
        section('pose_floor_px: "2 px"').encode(),
        "pose_floor_px must be a number, got '2 px'",
    ),
    "retired rotation floor": (
        section("pose_floor_rotation_px: 1.8").encode(),
        "unknown parameter 'pose_floor_rotation_px': replaced by pose_systematic_px (this "
        "camera's systematic error, default 0: the covariance now comes from the inliers and the "
        "model checks) and pose_floor_px (a lower bound on the pixel noise); see "
        "docs/real-cameras.md",
    ),
    "zero pixel limit": (
        section("max_image_pixels: 0").encode(),
        "max_image_pixels=0 is out of range [1, 1073741824]",
    ),
    # issue 22: identity and prior maps
    "robot id with a space": (
        section('robot_id: "my robot"').encode(),
        "robot_id 'my robot' must be 1-64 characters of ASCII letters, digits or '_' (a robot "
        "id starts with a letter): it names folders, a ROS topic and pose-graph keys, e.g. robot1",
    ),
    # issue 38: one identity rule (a folder name, a topic token, a key everywhere)
    "robot id '..'": (section('robot_id: ".."').encode(), "robot_id '..' must be 1-64 characters"),
    "robot id 'x.y'": (section('robot_id: "x.y"').encode(), "robot_id 'x.y' must be 1-64"),
    "robot id starting with a digit": (
        section('robot_id: "1r"').encode(),
        "robot_id '1r' must be 1-64 characters",
    ),
    "session id '.'": (section('session_id: "."').encode(), "session_id '.' must be 1-64"),
    "session id with '@'": (section('session_id: "s@1"').encode(), "session_id 's@1' must be"),
    "fleet_peers naming a bad id": (
        section('fleet_peers: "b, ../c"').encode(),
        "fleet_peers robot '../c' must be 1-64 characters",
    ),
    "robot id with a slash": (section('robot_id: "/r1"').encode(), "robot_id '/r1' must be 1-64"),
    "session id too long": (
        section(f'session_id: "{"s" * 65}"').encode(),
        f"session_id '{'s' * 65}' must be 1-64 characters",
    ),
    "session id number": (section("session_id: 20261125").encode(), "session_id must be a string"),
    "prior maps a string": (
        section('prior_map_dirs: "/maps/a"').encode(),
        "prior_map_dirs must be a list of non-empty strings, got '/maps/a'",
    ),
    "prior maps an empty name": (
        section('prior_map_dirs: ["/maps/a", ""]').encode(),
        "prior_map_dirs must be a list of non-empty strings, got ['/maps/a', '']",
    ),
    "loop per map a string": (
        section('loop_per_map: "yes"').encode(),
        "loop_per_map must be true or false, got 'yes'",
    ),
    "loop per map a number": (
        section("loop_per_map: 1").encode(),
        "loop_per_map must be true or false, got 1",
    ),
    # issue 46: the re-rank cascade and its learned floor
    "cascade a string": (
        section('rerank_cascade: "on"').encode(),
        "rerank_cascade must be true or false, got 'on'",
    ),
    "learned floor a number": (
        section("learned_floor: 0").encode(),
        "learned_floor must be true or false, got 0",
    ),
    # issue 37: the wait for a depth image
    "negative depth delay": (
        section("depth_max_delay: -0.1").encode(),
        "depth_max_delay=-0.1 is out of range [0.0, 10.0]",
    ),
    "depth delay too long": (
        section("depth_max_delay: 60.0").encode(),
        "depth_max_delay=60.0 is out of range [0.0, 10.0]",
    ),
    "nan depth delay": (
        section("depth_max_delay: .nan").encode(),
        "depth_max_delay must be a finite number",
    ),
    "string depth delay": (
        section('depth_max_delay: "0.5 s"').encode(),
        "depth_max_delay must be a number, got '0.5 s'",
    ),
    "list depth delay": (
        section("depth_max_delay: [0.5]").encode(),
        "depth_max_delay must be a number, got [0.5]",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_params_file(tmp_path: Path, case: str) -> None:
    content, message = CASES[case]
    path = tmp_path / "params.yaml"
    path.write_bytes(content)
    with pytest.raises(ConfigError, match=re.escape(message)) as info:
        read_params_file(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("kind", ["missing", "folder"])
def test_params_file_that_is_not_a_file(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "params.yaml"
    if kind == "folder":
        path.mkdir()
    with pytest.raises(ConfigError, match=re.escape(f"cannot read parameter file {path}")):
        read_params_file(path)


@pytest.mark.parametrize("kind", ["missing", "folder", "relative missing", "readable"])
def test_node_params_file_flag_is_checked_before_rcl(tmp_path: Path, monkeypatch, kind) -> None:
    # Issue 17 #3: rcl raised an RCLError traceback for a --params-file that does not exist.
    monkeypatch.chdir(tmp_path)
    (tmp_path / "folder").mkdir()
    (tmp_path / "readable.yaml").write_text(section("top_k: 3"))
    path = {
        "missing": str(tmp_path / "nope.yaml"),
        "folder": str(tmp_path / "folder"),
        "relative missing": "config/vpr_node.yaml",
        "readable": "readable.yaml",
    }[kind]
    args = ["vpr_node", "--ros-args", "-p", "top_k:=3", "--params-file", path]
    problem = params_file_problem(args)
    if kind == "readable":
        assert problem is None
        return
    what = {
        "missing": "does not exist",
        "folder": "is a folder",
        "relative missing": f"does not exist (relative to {tmp_path})",
    }[kind]
    assert problem == (
        f"--params-file {path} {what}: give a parameter file, e.g. the installed one, "
        "$(ros2 pkg prefix pair_vpr_ros)/share/pair_vpr_ros/config/vpr_node.yaml"
    )
    assert params_file_problem(["vpr_node", "--params-file"]) is None  # rcl's to report


def test_node_refuses_a_params_file_with_a_key_given_twice(tmp_path: Path) -> None:
    """Issue 25 #6: rcl keeps the last of two values of one key without a word."""
    path = tmp_path / "twice.yaml"
    path.write_text(section("top_k: 3\ntop_k: 20"))
    assert params_file_problem(["vpr_node", "--ros-args", "--params-file", str(path)]) == (
        f"--params-file {path}: 'top_k' is given twice (lines 3 and 4): keep one (YAML would "
        "use the last one without a word)"
    )
    path.write_text(section("top_k: 3\nmode: mapping"))
    assert params_file_problem(["vpr_node", "--ros-args", "--params-file", str(path)]) is None
