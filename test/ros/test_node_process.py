"""`vpr_node` as a process: clean stops on SIGINT / SIGTERM, one clear error without weights,
and the colcon install layout that `ros2 run pair_vpr_ros vpr_node` resolves."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.weights import RELEASED

ROOT = Path(__file__).resolve().parents[2]
NODE = [sys.executable, "-m", "pair_vpr_ros.ros.node", "--ros-args"]
ENV = {**os.environ, "RCUTILS_LOGGING_BUFFERED_STREAM": "0", "PYTHONUNBUFFERED": "1"}

pytestmark = pytest.mark.slow  # node processes, signals, a colcon build


def start_command(
    cmd: list[str], timeout: float = 60.0, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen, threading.Thread, list[str]]:
    """Start `cmd` (a node; environment `env`, default ENV) and wait until it logs "ready:" ->
    (process, output reader, its output lines so far); a process that is not ready in
    `timeout` s is stopped and fails."""
    proc = subprocess.Popen(
        cmd, cwd=ROOT, env=env or ENV, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    lines: list[str] = []
    ready = threading.Event()

    def read() -> None:
        for line in proc.stdout:
            lines.append(line)
            if "ready:" in line:
                ready.set()
        ready.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    if not (ready.wait(timeout) and proc.poll() is None):
        proc.terminate()
        proc.wait(30.0)
        pytest.fail("".join(lines))
    return proc, reader, lines


def start(*args: str) -> tuple[subprocess.Popen, threading.Thread, list[str]]:
    """Start the node once it is ready -> (process, output reader, its output lines so far)."""
    return start_command([*NODE, *args])


# Ctrl-C under `ros2 launch` sends SIGINT twice (the terminal's and launch's copy), then SIGTERM:
# a later signal must not break off the shutdown and its map save.
@pytest.mark.parametrize(
    "signals",
    [[signal.SIGINT], [signal.SIGTERM], [signal.SIGINT] * 10 + [signal.SIGTERM]],
    ids=["SIGINT", "SIGTERM", "repeated"],
)
def test_signal_stops_cleanly_and_saves(signals, tmp_path):
    proc, reader, lines = start(
        "-p", "weights:=random-tiny", "-p", f"map_dir:={tmp_path / 'map'}",
        "-p", "save_on_shutdown:=true",
    )  # fmt: skip
    time.sleep(0.5)  # spinning by now (a signal during start-up is covered by main() too)
    for sig in signals:  # 10 ms apart: some land while the node shuts down
        proc.send_signal(sig)
        time.sleep(0.01)
    code = proc.wait(30.0)
    reader.join(10.0)
    out = "".join(lines)
    assert code == 0, out
    assert "Traceback" not in out and "on shutdown: saved 0 keyframes" in out
    with PlaceMap.load(tmp_path / "map", read_only=True) as saved:
        assert len(saved) == 0


def run_without_weights(command: list[str], env: dict, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(command, env=env, cwd=cwd, capture_output=True, text=True, timeout=120)


def test_missing_weights_is_one_clear_error():
    done = run_without_weights(NODE[:-1], ENV, ROOT)
    assert done.returncode == 1
    errors = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and "Traceback" not in done.stderr
    folder = Path(ENV["XDG_DATA_HOME"]) / "pair_vpr_ros"  # test/conftest.py: never exists
    assert errors[0].startswith("[ERROR]") and errors[0].endswith(
        "[vpr_node]: cannot start: no Pair-VPR weights found; looked in parameter weights "
        "(-p weights:=PATH): not given; $PAIRVPR_WEIGHTS: not set; "
        f"{folder}: no such folder. Set one of these to a checkpoint (.pth) or put exactly one "
        f".pth into {folder}; {RELEASED}"
    )


def test_colcon_install_resolves_like_ros2_run(tmp_path):
    pytest.importorskip("colcon_core", reason="colcon-common-extensions is not installed")
    colcon = shutil.which("colcon") or str(Path(sys.executable).with_name("colcon"))
    if not Path(colcon).exists():
        pytest.skip("the colcon command is not installed next to this Python")
    src = tmp_path / "src" / "pair_vpr_ros"
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
    src.mkdir(parents=True)
    for name in ("setup.py", "setup.cfg", "package.xml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("resource", "config", "launch", "pair_vpr_ros"):
        shutil.copytree(ROOT / name, src / name, ignore=ignore)
    build = subprocess.run(
        [colcon, "build", "--base-paths", "src", "--build-base", "build",
         "--install-base", "install"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300, env=ENV,
    )  # fmt: skip
    assert build.returncode == 0, build.stdout + build.stderr
    prefix = tmp_path / "install" / "pair_vpr_ros"
    site = next(prefix.glob("lib/python*/site-packages"))
    env = {**ENV, "AMENT_PREFIX_PATH": str(prefix), "PYTHONPATH": str(site)}
    resolve = (
        "from ament_index_python import get_package_prefix, get_package_share_directory as s;"
        "import pair_vpr_ros; print(get_package_prefix('pair_vpr_ros')); print(s('pair_vpr_ros'));"
        "print(pair_vpr_ros.__file__)"
    )
    where = subprocess.run(
        [sys.executable, "-c", resolve], env=env, cwd=tmp_path, capture_output=True, text=True
    )
    assert where.returncode == 0, where.stderr
    found, share, module = where.stdout.split()
    assert Path(found) == prefix and Path(module).is_relative_to(site)
    config = (ROOT / "config" / "vpr_node.yaml").read_text()
    assert (Path(share) / "config" / "vpr_node.yaml").read_text() == config
    assert (Path(share) / "config" / "demo.yaml").is_file()
    assert (Path(share) / "config" / "posegraph_node.yaml").is_file()
    assert os.access(Path(found) / "lib" / "pair_vpr_ros" / "posegraph_node", os.X_OK)
    assert (Path(share) / "launch" / "vpr_node.launch.py").is_file()
    exe = Path(found) / "lib" / "pair_vpr_ros" / "vpr_node"
    assert os.access(exe, os.X_OK)
    done = run_without_weights([str(exe)], env, tmp_path)
    assert done.returncode == 1 and "cannot start: no Pair-VPR weights found" in done.stderr


@pytest.mark.parametrize("module", ["pair_vpr_ros.ros.entry", "pair_vpr_ros.ros.node"])
def test_ctrl_c_while_modules_import_stops_quietly(module):
    # Issue 17 #2: Ctrl-C in the first second or two printed a KeyboardInterrupt traceback and
    # exited with -2. `-X importtime` writes a line as each module finishes importing: the
    # signal goes out once rclpy is in and the node module (torch, ...) is still importing.
    # Issue 25 #5: the same for `python -m pair_vpr_ros.ros.node`.
    entry = [sys.executable, "-X", "importtime", "-m", module]
    proc = subprocess.Popen(
        [*entry, "--ros-args", "-p", "weights:=random-tiny"], cwd=ROOT, env=ENV, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
    )  # fmt: skip
    guard = threading.Timer(120.0, proc.kill)  # never hang the suite if the line never comes
    guard.start()
    lines = []
    for line in proc.stderr:
        lines.append(line)
        if re.search(r"\|\s*rclpy$", line.rstrip()):  # nested: "|     rclpy"
            proc.send_signal(signal.SIGINT)
            break
    out, err = proc.communicate(timeout=120)
    guard.cancel()
    text = out + "".join(lines) + err
    assert proc.returncode == 0, text
    assert "Traceback" not in text and "KeyboardInterrupt" not in text
    assert "ready:" not in text  # it stopped while starting


@pytest.mark.parametrize("content", [None, "a: [b\n"], ids=["missing", "broken yaml"])
def test_a_params_file_that_cannot_be_used_is_one_clear_error(tmp_path, content):
    # Issue 17 #3: an RCLError traceback.
    path = tmp_path / "vpr_node.yaml"
    if content is not None:
        path.write_text(content)
    done = subprocess.run(
        [*NODE, "--params-file", str(path), "-p", "weights:=random-tiny"], cwd=ROOT, env=ENV,
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    errors = [line for line in done.stderr.splitlines() if "[vpr_node]" in line]
    expected = (
        f"cannot start: --params-file {path} does not exist: give a parameter file"
        if content is None
        else f"cannot start: failed to initialize rcl: Couldn't parse params file: "
        f"'--params-file {path}'"
    )
    assert len(errors) == 1 and expected in errors[0], done.stderr
