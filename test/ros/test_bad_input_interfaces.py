"""Bad input, typed interfaces: a node whose message package is missing runs with one clear
warning and every other output; the build script refuses a venv it cannot build with, saying
what to do."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from bag_fixtures import synthetic_images
from node_harness import wait_for
from rclpy.impl.rcutils_logger import RcutilsLogger
from test_node_process import start_command

from pair_vpr_ros.ros import outputs

ROOT = Path(__file__).resolve().parents[2]
MISSING = "No module named 'pair_vpr_ros_interfaces'"
WARNING = (
    "/loop_closure/typed is off: the message package pair_vpr_ros_interfaces cannot be imported "
    f"({MISSING}); build it with `make setup` (pip install) or `colcon build` in your ROS "
    "workspace, and start the node from its environment (docs/interfaces.md). Every other "
    "loop-closure topic is on."
)
# Runs the node as `python -m pair_vpr_ros.ros.node` would, with the package made unimportable.
BLOCKED = """
import runpy, sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "pair_vpr_ros_interfaces":
            raise ModuleNotFoundError("No module named 'pair_vpr_ros_interfaces'")
sys.meta_path.insert(0, Block())
sys.argv = ["vpr_node", *sys.argv[1:]]
runpy.run_module("pair_vpr_ros.ros.node", run_name="__main__")
"""


def test_without_the_message_package_the_node_warns_once_and_runs(harness, monkeypatch):
    monkeypatch.setattr(outputs, "LoopClosure", None)
    monkeypatch.setattr(outputs, "TYPED_MISSING", MISSING)
    warnings: list[str] = []
    original = RcutilsLogger.warning
    monkeypatch.setattr(
        RcutilsLogger, "warning", lambda self, text, **kw: (warnings.append(text), original(
            self, text, **kw))[1]
    )  # fmt: skip
    h = harness()
    assert h.node.outputs.typed is None
    assert [w for w in warnings if "typed" in w] == [WARNING]
    places = synthetic_images(3, size=32)
    h.publish([places[i] for i in (0, 1, 2, 0)])
    h.processed(4)
    wait_for(lambda: len(h.got["loop_closure/json"]) == 1)
    assert [list(m.data) for m in h.got["loop_closure"]] == [[103.0, 100.0]]
    assert json.loads(h.got["loop_closure/json"][0].data)["match_id"] == 0
    assert [w for w in warnings if "typed" in w] == [WARNING]  # once, not per loop


@pytest.mark.slow
def test_a_node_process_without_the_package_starts_with_the_warning():
    proc, reader, lines = start_command(
        [sys.executable, "-c", BLOCKED, "--ros-args", "-p", "weights:=random-tiny"], timeout=120.0
    )
    proc.terminate()
    proc.wait(30.0)
    reader.join(10.0)
    typed = [line for line in lines if "typed" in line]
    assert len(typed) == 1 and typed[0].rstrip().endswith(f"[vpr_node]: {WARNING}"), lines
    assert typed[0].startswith("[WARN]")


def build_script(venv: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["bash", str(ROOT / "scripts" / "build_interfaces.sh")],
        env={**os.environ, "VENV": str(venv)}, capture_output=True, text=True, timeout=60,
    )  # fmt: skip


def test_build_script_without_a_venv_says_to_run_setup(tmp_path):
    done = build_script(tmp_path / "nothing")
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr == (
        f"setup: error: no Python at {tmp_path / 'nothing'}/bin/python: make setup creates the "
        "venv (or give VENV=the venv with the ros and interfaces extras)\n"
    )


def test_build_script_without_colcon_names_the_extra(tmp_path):
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "python").symlink_to(sys.executable)
    done = build_script(tmp_path)
    assert done.returncode == 1 and done.stdout == ""
    assert done.stderr == (
        f"setup: error: colcon is not installed in {tmp_path}: pip install -e "
        "'.[ros,interfaces]' (make setup does), or set PAIRVPR_INTERFACES=skip to go without "
        "loop_closure/typed\n"
    )
