"""The node's entry point finds this venv's C libraries however the node was started: a node
started from a second environment (another venv's `ros2 launch` / `ros2 run`: its own
LD_LIBRARY_PATH, the wheels' start-up hook marked done) starts itself again with this venv's
lib/ and publishes typed loops; where even that cannot help, typed is off with one warning and
the node runs (docs/interfaces.md)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
from test_node_process import ENV, start_command

from pair_vpr_ros.ros import entry

VENV_LIB = Path(sys.prefix) / "lib"
OURS = "libpair_vpr_ros_interfaces__"
NODE = [sys.executable, "-m", "pair_vpr_ros.ros.node", "--ros-args", "-p", "weights:=random-tiny"]


def test_a_missing_library_folder_goes_first_and_only_once(monkeypatch):
    monkeypatch.setattr(entry, "library_dirs", lambda: ["/venv/lib", "/venv/ros_rcl.libs"])
    again = entry.find_own_libraries({"LD_LIBRARY_PATH": "/other/lib:/venv/ros_rcl.libs"})
    assert again["LD_LIBRARY_PATH"] == "/venv/lib:/other/lib:/venv/ros_rcl.libs"
    assert again[entry.REEXEC_MARK] == "1"
    assert entry.find_own_libraries(again) is None  # started again: never a second time
    assert entry.find_own_libraries({"LD_LIBRARY_PATH": "/venv/ros_rcl.libs:/venv/lib"}) is None


def test_outside_a_venv_nothing_is_added(monkeypatch):
    monkeypatch.setattr(sys, "prefix", sys.base_prefix)
    assert entry.library_dirs() == []
    assert entry.find_own_libraries({"LD_LIBRARY_PATH": ""}) is None


def second_environment(tmp_path: Path) -> dict[str, str]:
    """What a node inherits from another venv's `ros2 launch`: that venv's lib/ (here: this
    venv's ROS libraries without the typed messages' ones) and the wheels' hook marked done."""
    other = tmp_path / "other_venv_lib"
    other.mkdir()
    for lib in VENV_LIB.glob("*.so*"):
        if not lib.name.startswith(OURS):
            (other / lib.name).symlink_to(lib)
    wheels = sorted(str(p) for p in VENV_LIB.glob("python3*/site-packages/ros_*.libs"))
    return {
        **ENV,
        "LD_LIBRARY_PATH": os.pathsep.join([str(other), *wheels]),
        "_ROS_WHEELS_BOOTSTRAP_COMPLETE": "1",
    }


def run_node(env: dict[str, str]) -> list[str]:
    proc, reader, lines = start_command(NODE, timeout=120.0, env=env)
    proc.terminate()
    assert proc.wait(30.0) == 0, lines
    reader.join(10.0)
    return lines


@pytest.fixture
def our_libraries(typed_messages):
    if sys.prefix == sys.base_prefix or not list(VENV_LIB.glob(f"{OURS}*.so")):
        pytest.skip("the typed messages are not built into this venv's lib/ (make setup)")


@pytest.mark.slow
def test_from_a_second_environment_the_node_finds_its_typed_messages(tmp_path, our_libraries):
    lines = run_node(second_environment(tmp_path))
    assert not [line for line in lines if "typed is off" in line], lines
    assert not [line for line in lines if "Traceback" in line], lines


@pytest.mark.slow
def test_where_they_still_cannot_load_typed_is_off_with_one_warning(tmp_path, our_libraries):
    # the mark says "already started again": as a node whose own lib/ has no typed messages
    env = {**second_environment(tmp_path), entry.REEXEC_MARK: "1"}
    lines = run_node(env)
    typed = [line for line in lines if "typed is off" in line]
    assert len(typed) == 1, lines
    assert typed[0].startswith("[WARN]")
    assert "(UnsupportedTypeSupport: Could not import 'rosidl_typesupport_c' for package " \
        "'pair_vpr_ros_interfaces')" in typed[0]  # fmt: skip
    assert not [line for line in lines if "Traceback" in line], lines
