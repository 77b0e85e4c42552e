"""`make demo-live`: the demo through a real ROS 2 graph.

vpr_node and posegraph_node run as two processes talking over DDS, started with exactly the
parameters and remappings vpr_posegraph.launch.py gives them for the demo's arguments (both read
`ros.launch_table`; with `--launch`, `ros2 launch` itself starts them). `pairvpr-bag-play` plays
the demo bag into them in (scaled) real time; `ros.loop_recorder` hears the loops, the factors
and the corrected path. At the end both nodes get SIGINT and must exit 0, and the run is
compared with `make demo`'s replay (loop pairs, factors) and the bag's ground truth (ATE).

    python -m pair_vpr_ros.demo.live demo_out/demo_world.mcap --replay demo_out/replay \\
        --out demo_out/live --rate 1.0
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from pair_vpr_ros.cli import nonnegative_float, positive_float, run_cli
from pair_vpr_ros.demo.bag import (
    CAMERA_INFO_TOPIC,
    DEPTH_TOPIC,
    GROUND_TRUTH_TOPIC,
    IMAGE_TOPIC,
    ODOM_TOPIC,
)
from pair_vpr_ros.errors import PairVPRError, UsageError
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.bags.reader import read_poses
from pair_vpr_ros.offline.report.trajectories import Trajectory, trajectory_errors
from pair_vpr_ros.ros.launch_table import PACKAGE, defaults, node_setups, ros_args

ROOT = Path(__file__).resolve().parents[2]
LAUNCH = "vpr_posegraph.launch.py"
DEMO_MODEL = ROOT / "pair_vpr_ros" / "demo" / "assets" / "demo-small.pth"
DEMO_CAMERA = "[0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5]"  # optical frame 1.6 m above base_link
START = "import sys; from pair_vpr_ros.ros.entry import {0}; sys.exit({0}())"
# A process started from a background job inherits SIGINT ignored, and `ros2 launch` then never
# hears the stop: every child starts with SIGINT at its default, as from a terminal.
SIGINT_DEFAULT = [
    sys.executable, "-c",
    "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
    "os.execvp(sys.argv[1], sys.argv[1:])",
]  # fmt: skip


def demo_arguments(weights: str, params_file: str) -> dict[str, str]:
    """The README's launch command on the demo bag: its topics, the demo model and settings."""
    values = defaults(LAUNCH, ROOT / "config")
    values.update(
        weights=weights, params_file=params_file, image=IMAGE_TOPIC, depth=DEPTH_TOPIC,
        camera_info=CAMERA_INFO_TOPIC, odom=ODOM_TOPIC, camera_to_base=DEMO_CAMERA,
    )  # fmt: skip
    return values


class Process:
    """A child process whose output is echoed with a prefix and searched for `ready:`."""

    def __init__(self, name: str, command: list[str], env: dict[str, str]) -> None:
        self.name, self.ready = name, 0
        self.proc = subprocess.Popen(
            [*SIGINT_DEFAULT, *command], cwd=ROOT, env=env, text=True, stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.ready += "]: ready: " in line
            print(f"[{self.name}] {line}", end="", flush=True)

    def stop(self, timeout: float = 60.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:  # its whole session: `ros2 launch` leaves no orphans
            os.killpg(self.proc.pid, signal.SIGKILL)
            code = self.proc.wait()
        self._reader.join(5.0)
        return code


def start_nodes(values: dict[str, str], out: Path, launch: bool, env: dict) -> list[Process]:
    if launch:
        if shutil.which("ros2") is None:
            raise UsageError(
                "LAUNCH=1 needs `ros2 launch` on PATH (a ROS install, or the environment of "
                "scripts/ros_cli_env.sh, docs/launch.md)"
            )
        given = [f"{k}:={v}" for k, v in values.items() if v]  # '' = the launch's default
        command = ["ros2", "launch", PACKAGE, LAUNCH, *given]
        return [Process("ros2 launch", command, env)]
    return [
        Process(s.name, [sys.executable, "-c", START.format(s.executable), *ros_args(s, out)], env)
        for s in node_setups(LAUNCH, values)
    ]


def wait_until(what: str, condition, timeout: float, processes: list[Process]) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if any(p.proc.poll() is not None for p in processes):
            raise PairVPRError(f"a node exited while waiting for {what}")
        if time.monotonic() > deadline:
            raise PairVPRError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.2)


def replay_loops(replay: Path) -> tuple[set[tuple[float, float]], int]:
    """`make demo`'s accepted loop pairs (query, match stamps, ms) and how many had a pose."""
    pairs, factors = set(), 0
    with open(replay / "loops.csv", newline="") as f:
        for row in csv.DictReader(f):
            if row["accepted"] == "True":
                pair = (float(row["query_stamp"]), float(row["match_stamp"]))
                pairs.add((round(pair[0], 3), round(pair[1], 3)))
                factors += not math.isnan(float(row["tx"] or "nan"))
    return pairs, factors


def live_loops(records: list[dict]) -> set[tuple[float, float]]:
    return {(round(r["query_stamp"], 3), round(r["match_stamp"], 3))
            for r in records if r.get("accepted")}  # fmt: skip


def bag_track(bag: Path, topic: str) -> Trajectory:
    with open_bag(bag) as reader:
        track, _ = read_poses(reader, topic)
    stamps, poses = track.items()
    return Trajectory(np.asarray(stamps, dtype=float), np.asarray(poses, dtype=float))


def run(args: argparse.Namespace) -> int:
    from pair_vpr_ros.ros.loop_recorder import LoopRecorder

    out, started = args.out, time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "PYTHONUNBUFFERED": "1",
           "RCUTILS_LOGGING_BUFFERED_STREAM": "0"}  # fmt: skip
    values = demo_arguments(str(args.weights), str(args.params_file))
    frames = sum(1 for _ in bag_track(args.bag, ODOM_TOPIC).stamps)
    processes = start_nodes(values, out, args.launch, env)
    recorder, codes = None, []
    try:
        wait_until("both nodes' `ready:`", lambda: sum(p.ready for p in processes) >= 2,
                   args.timeout, processes)  # fmt: skip
        recorder = LoopRecorder(values["loop_closure"])
        inputs = [values[k] for k in ("image", "depth", "camera_info", "odom")]
        play = [sys.executable, "-m", "pair_vpr_ros.ros.bag_play", str(args.bag),
                "--rate", str(args.rate), "--wait", "60", "--wait-for", *inputs]  # fmt: skip
        subprocess.run(play, cwd=ROOT, env=env, check=True, timeout=args.timeout)
        time.sleep(2.0)  # the last frames in flight, a /diagnostics message about them
        done = lambda: recorder.counter("frames_received") > 0 and (  # noqa: E731
            recorder.counter("frames_processed") + recorder.counter("frames_dropped")
            >= recorder.counter("frames_received"))  # fmt: skip
        wait_until("vpr_node to process every frame it heard", done, args.timeout, processes)
        time.sleep(args.settle)  # the last factors through the graph, a last corrected_path
    finally:
        codes = [p.stop() for p in processes]
        if recorder is not None:
            recorder.close()
    return report(args, recorder, frames, codes, time.monotonic() - started)


def report(args, recorder, frames: int, codes: list[int], seconds: float) -> int:
    """Compare with `make demo` and the ground truth; write summary.json; the exit code."""
    demo_pairs, demo_factors = replay_loops(args.replay)
    live = live_loops(recorder.records)
    stamps, poses = recorder.path_poses()
    truth = bag_track(args.bag, GROUND_TRUTH_TOPIC)
    ate = None
    if stamps:
        ate = trajectory_errors(Trajectory(np.asarray(stamps), np.asarray(poses)), truth).ate_rmse
    odom_ate = trajectory_errors(bag_track(args.bag, ODOM_TOPIC), truth).ate_rmse
    children = resource.getrusage(resource.RUSAGE_CHILDREN)  # the nodes and the player
    summary = {
        "seconds": round(seconds, 1), "rate": args.rate, "launch": args.launch,
        "cpu_seconds_children": round(children.ru_utime + children.ru_stime, 1),
        "frames": frames, "frames_received": recorder.counter("frames_received"),
        "frames_processed": recorder.counter("frames_processed"),
        "frames_dropped": recorder.counter("frames_dropped"),
        "frames_without_depth": recorder.counter("frames_without_depth"),
        "loops_live": len(live), "loops_demo": len(demo_pairs),
        "loops_same": len(live & demo_pairs), "loops_only_live": len(live - demo_pairs),
        "loops_only_demo": len(demo_pairs - live),
        "factors_live": recorder.factors, "factors_demo": demo_factors,
        "loops_posed_by_node": sum(recorder.counter(f"loops_pose_{k}")
                                   for k in ("metric", "metric_odometry", "scale_free")),
        "posegraph_nodes": len(stamps), "ate_corrected_m": ate, "ate_odometry_m": odom_ate,
        "exit_codes": codes,
    }  # fmt: skip
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    (args.out / "loops.json").write_text(json.dumps(recorder.records))
    print(f"demo-live: {summary['seconds']} s (rate {args.rate:g}); frames received "
          f"{summary['frames_received']}/{frames}, processed {summary['frames_processed']}, "
          f"dropped {summary['frames_dropped']}; loops "
          f"{len(live)} live vs {len(demo_pairs)} make demo, {summary['loops_same']} the same; "
          f"factors {recorder.factors} vs {demo_factors}; pose graph ATE "
          f"{ate if ate is None else round(ate, 3)} m (odometry {odom_ate:.3f} m); node exit "
          f"codes {codes}; {args.out / 'summary.json'}")  # fmt: skip
    ok = all(c == 0 for c in codes) and ate is not None and recorder.factors >= 0.9 * demo_factors
    return 0 if ok else 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="demo-live", description=__doc__.split("\n")[0])
    p.add_argument("bag", type=Path, help="the demo bag (make demo writes it)")
    p.add_argument("--replay", type=Path, required=True, help="make demo's replay folder")
    p.add_argument("--out", type=Path, required=True, help="folder for summary.json")
    p.add_argument("--weights", type=Path, default=DEMO_MODEL, help="the demo model")
    p.add_argument("--params-file", type=Path, default=ROOT / "config/demo.yaml")
    p.add_argument("--rate", type=positive_float, default=1.0, help="bag play speed")
    p.add_argument("--launch", action="store_true", help="start the nodes with `ros2 launch`")
    p.add_argument("--timeout", type=positive_float, default=600.0, help="seconds per step")
    p.add_argument("--settle", type=nonnegative_float, default=3.0,
                   help="seconds to wait after the last frame")  # fmt: skip
    return p


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), run, argv)


if __name__ == "__main__":
    sys.exit(main())
