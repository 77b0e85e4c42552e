"""Sharing the CPU (issue 50): the demo replay and the node's keyframe latency, quiet and beside
busy processes, for each CPU thread count (`num_threads`, `model/threads.py`).

    python benchmarks/bench_shared_cpu.py --hogs 0,2 --threads auto,2 --json shared.json
    python benchmarks/bench_shared_cpu.py --parts latency --models vitb-int8 --threads 1,2

Busy processes ("hogs"): N busy loops this benchmark starts before a run and stops after it,
at its own priority, each in a session of its own (as another program would be); each also
ends by itself after --hog-limit seconds, so none outlives a killed benchmark. Every run is a
child process of its own (thread pools are sized once per process), started after the hogs.

- replay: make demo's `pairvpr-bag-replay` of the demo bag (config/demo.yaml, depth, the
  shipped model) with `--threads`: wall time and CPU seconds (user + system) of the process,
  and its loops, precision and recall (the same for every thread count, or something is wrong).
- latency: the node's map thread (`ros.maps.MapControl` with the node's per-thread context)
  over frames of the demo bag with their depth and intrinsics, as the node gets them, one frame
  every --period s (back to back when a frame takes longer): each keyframe's time from
  hand-over to outcome, p50 / p95 over the keyframes that re-ranked candidates, and the CPU
  seconds per frame; config/demo.yaml's detector. Models: `demo` (the shipped model, torch
  fp32, top 5), `vitb-int8` (ViT-B/322 with random weights on OpenVINO int8, top 2: speed does
  not depend on the weights; the first run exports and calibrates it into the OpenVINO cache,
  minutes, once) and `vitb-torch` (the same on torch fp32).

Without --bag the demo bag is written first (`pairvpr-make-demo-bag`, seed 7, 600 frames).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEMO_WEIGHTS = ROOT / "pair_vpr_ros" / "demo" / "assets" / "demo-small.pth"
DEMO_PARAMS = ROOT / "config" / "demo.yaml"
HOG = "import sys, time\nend = time.monotonic() + float(sys.argv[1])\nwhile time.monotonic() < end:\n    pass\n"  # noqa: E501
# model -> weights, backend, precision, every n-th frame of the bag, frames, seconds between
# frames, candidates re-ranked (ViT-B: 2, one OpenVINO chunk, what the ViT-B soak's budget scored)
MODELS = {
    "demo": (str(DEMO_WEIGHTS), "torch", "fp32", 2, 300, 0.1, 5),
    "vitb-int8": ("random-B", "openvino", "int8", 12, 50, 1.5, 2),
    "vitb-torch": ("random-B", "torch", "fp32", 12, 30, 5.0, 2),
}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bag", type=Path, help="the demo bag (default: written to a temp folder)")
    p.add_argument("--parts", default="replay,latency", help="replay, latency (%(default)s)")
    p.add_argument(
        "--models", default="demo,vitb-int8",
        help=f"latency models, of {', '.join(MODELS)} (%(default)s)",
    )  # fmt: skip
    p.add_argument("--threads", default="auto,2", help="thread counts; auto = 0 (%(default)s)")
    p.add_argument("--hogs", default="0,2", help="busy processes beside each run (%(default)s)")
    p.add_argument("--repeat", type=int, default=1, help="runs of each setting (%(default)s)")
    p.add_argument("--hog-limit", type=float, default=1200.0, help="a hog's longest life, s")
    p.add_argument(
        "--hog-session", choices=("own", "same"), default="own",
        help="busy processes each in a session of their own (shared between sessions first, "
        "autogroup) or in this benchmark's session (shared between threads) (%(default)s)",
    )  # fmt: skip
    p.add_argument(
        "--period", type=float, default=None,
        help="latency: seconds between frames (default: 0.1 demo, 1.5 ViT-B int8, 5 torch)",
    )  # fmt: skip
    p.add_argument("--frames", type=int, help="latency: frames per run (default: per model)")
    p.add_argument(
        "--before", type=Path, metavar="TREE",
        help="replay: also run the package of this source tree (e.g. `git archive main` "
        "unpacked), as it was, beside each thread count: the baseline measured alike",
    )  # fmt: skip
    p.add_argument("--json", type=Path, help="also write every run's figures here")
    p.add_argument("--child", nargs=3, metavar=("MODEL", "THREADS", "BAG"), help=argparse.SUPPRESS)
    return p.parse_args(argv)


def start_hogs(n: int, limit: float, own_session: bool = True) -> list[subprocess.Popen]:
    """`n` busy loops, each in a session of its own (default): on Linux with autogroup
    scheduling (the desktop and container default) the CPU is shared between sessions first,
    as between a robot's programs started apart (services, other terminals); a run's fair
    share is then its session's, however many threads it has. `own_session=False`: in this
    benchmark's session, as programs started from one terminal or launch file, where the CPU
    is shared between threads."""
    cmd = [sys.executable, "-c", HOG, str(limit)]
    return [subprocess.Popen(cmd, start_new_session=own_session) for _ in range(n)]


def stop_hogs(hogs: list[subprocess.Popen]) -> None:
    for h in hogs:
        h.kill()
    for h in hogs:
        h.wait()


def load_avg() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def replay_run(bag: Path, threads: str, out: Path, tree: Path | None = None) -> dict:
    """make demo's replay in a child process -> wall, CPU, and its figures. `tree`: run the
    package of that source tree instead (another commit, as it was: no --threads)."""
    cmd = [
        sys.executable, "-m", "pair_vpr_ros.offline.replay.cli", str(bag),
        "--topic", "/camera/image_raw", "--weights", str(DEMO_WEIGHTS),
        "--params-file", str(DEMO_PARAMS), "--pose-topic", "/odom",
        "--gt-topic", "/ground_truth", "--out", str(out), "--overwrite", "--quiet",
    ]  # fmt: skip
    env = dict(os.environ)
    if tree is None:
        cmd += ["--threads", threads]
    else:
        env["PYTHONPATH"] = str(tree)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tree)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"replay failed ({done.returncode}): {done.stderr[-2000:]}")
    summary = json.loads((out / "summary.json").read_text())
    ev = summary.get("evaluation") or {}
    return {
        "wall_s": wall,
        "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
        "loop_s": summary["seconds"],
        "threads": summary.get("threads") or threads,
        "loops": summary["loops"],
        "precision": ev.get("precision"),
        "recall": ev.get("recall"),
    }


def latency_child(model_name: str, threads: int, bag: Path, period: float, frames: int) -> dict:
    """In the child: the node's MapControl over the bag's frames -> latency figures."""
    from pair_vpr_ros import params
    from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
    from pair_vpr_ros.model.threads import applied_threads
    from pair_vpr_ros.offline.bags.sources import FrameCounts, source_frames
    from pair_vpr_ros.ros.maps import MapControl
    from pair_vpr_ros.ros.runtime import precision_context
    from pair_vpr_ros.weights import load_model

    weights, backend, precision, stride, default_frames, _, top_k = MODELS[model_name]
    frames = frames or default_frames
    model = load_model(weights, backend=backend, precision=precision, num_threads=threads)
    values = {**params.read_params_file(DEMO_PARAMS), "top_k": top_k}
    config, geometry = params.detector_config(values), params.geometry_config(values)

    def factory() -> LoopClosurePipeline:
        return LoopClosurePipeline(model, config, geometry=geometry)

    maps = MapControl(factory, lambda level, text: None, lambda: precision_context("cpu", "fp32"))
    source = source_frames(bag, FrameCounts(), "/camera/image_raw", pose_topic="/odom")
    chosen = [f for i, f in enumerate(source) if i % stride == 0][:frames]
    latency, reranked = [], []
    cpu0, start = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    for i, frame in enumerate(chosen):
        time.sleep(max(0.0, start + i * period - time.perf_counter()))
        t0 = time.perf_counter()
        outcome, _ = maps.process(frame)
        latency.append(time.perf_counter() - t0)
        reranked.append(outcome.loop is not None)
    wall = time.perf_counter() - start
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    maps.close()
    ms = np.array(latency) * 1e3
    scored = ms[np.array(reranked)] if any(reranked) else ms
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    return {
        "threads": applied_threads(),
        "frames": len(ms),
        "reranked": int(sum(reranked)),
        "p50_ms": float(np.percentile(scored, 50)),
        "p95_ms": float(np.percentile(scored, 95)),
        "encode_only_p50_ms": float(np.median(ms[~np.array(reranked)])) if not all(reranked)
        else None,
        "wall_s": wall,
        "cpu_s": cpu,
        "cpu_per_frame_ms": 1e3 * cpu / len(ms),
    }  # fmt: skip


def latency_run(model: str, threads: str, bag: Path, args: argparse.Namespace) -> dict:
    period = args.period if args.period is not None else MODELS[model][5]
    cmd = [sys.executable, __file__, "--child", model, threads, str(bag), "--period", str(period)]
    cmd += ["--frames", str(args.frames)] if args.frames else []
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"latency run failed ({done.returncode}): {done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def demo_bag(folder: Path) -> Path:
    bag = folder / "demo_world.mcap"
    maker = Path(sys.executable).parent / "pairvpr-make-demo-bag"
    cmd = [str(maker), str(bag), "--seed", "7", "--frames", "600", "--force"]
    subprocess.run(cmd, check=True, capture_output=True)
    return bag


def fmt(row: dict) -> str:
    part, name = row["part"], row.get("model", "demo")
    head = f"| {part} | {name} | {row['threads']} | {row['hogs']} | {row['load']} |"
    if part == "replay":
        return (f"{head} {row['wall_s']:.1f} | {row['cpu_s']:.1f} | {row['loops']} loops, "
                f"precision {row['precision']:.3f}, recall {row['recall']:.3f} |")  # fmt: skip
    return (f"{head} {row['wall_s']:.1f} | {row['cpu_s']:.1f} | p50 {row['p50_ms']:.0f} ms, "
            f"p95 {row['p95_ms']:.0f} ms ({row['reranked']} of {row['frames']} re-ranked), "
            f"{row['cpu_per_frame_ms']:.0f} ms CPU a frame |")  # fmt: skip


def one_run(part: str, model: str, threads: str, hogs: int, bag: Path, tmp: Path, args) -> dict:
    """One run with `hogs` busy processes beside it -> its figures."""
    load = load_avg()
    running = start_hogs(hogs, args.hog_limit, args.hog_session == "own")
    try:
        if part == "replay":
            tree = args.before if threads == "before" else None
            row = replay_run(bag, threads, tmp / "replay", tree)
        else:
            row = latency_run(model, threads, bag, args)
    finally:
        stop_hogs(running)
    shown = row.get("threads") or ("auto" if threads == "0" else threads)
    return {**row, "part": part, "model": model, "hogs": hogs, "load": load, "threads": shown}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    if args.child:
        model, threads, bag = args.child
        print(json.dumps(latency_child(model, int(threads), Path(bag), args.period, args.frames)))
        return 0
    parts = args.parts.split(",")
    thread_list = ["0" if t == "auto" else t for t in args.threads.split(",")]
    before = ["before"] if args.before else []
    runs = [("replay", "demo", t) for t in before + thread_list] if "replay" in parts else []
    if "latency" in parts:
        runs += [("latency", m, t) for m in args.models.split(",") for t in thread_list]
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        bag = (args.bag or demo_bag(Path(tmp))).resolve()
        print("| part | model | threads | busy processes | load before | wall s | CPU s | "
              "result |\n|---|---|---|---|---|---|---|---|")  # fmt: skip
        # the repeats go round every setting in turn, so that a change in load hits them all
        for _ in range(args.repeat):
            for part, model, threads in runs:
                for hogs in [int(h) for h in args.hogs.split(",")]:
                    rows.append(one_run(part, model, threads, hogs, bag, Path(tmp), args))
                    print(fmt(rows[-1]), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
