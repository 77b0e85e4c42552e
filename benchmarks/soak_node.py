"""Soak test of `vpr_node`: synthetic 640x480 frames at 30 Hz into the running node for N minutes.

Starts the node as a subprocess (a checkpoint, the tiny random network by default, or with
`--vitb` a random-init ViT-B/322: the released model's size, so its timings are real), publishes
a camera that tours `--places` synthetic places (each shown for `--frames-per-place` frames) and
then tours them again, so loops come back every `places * frames_per_place / rate` seconds.
`--keyframe-interval S` makes every frame S seconds after the last encoded one a keyframe (the
configured keyframe rate) and `--budget-ms` sets the node's `rerank_budget_ms`.

It prints a row every `--sample` seconds and a summary: every frame accounted for (published =
lost before the node + received; received = invalid + rate-limited + dropped + processed +
failed + still queued), the deepest queue seen, keyframe latency over the whole run (the frame's
stamp to its loop record's arrival, every keyframe with candidates: the node publishes rejected
records too), candidates scored per keyframe, and the node's resident memory (VmRSS) against the
map's size. Memory must grow no faster than the map: RSS growth after warm-up <= map growth +
`--slack-mb`.

    python benchmarks/soak_node.py --minutes 2
    nice -n 19 python benchmarks/soak_node.py --minutes 10 --vitb --precision int8 \
        --keyframe-interval 4 --budget-ms 1500 --out soak.json --plot docs/soak_rss.png
    python benchmarks/soak_node.py --minutes 10 --weights pairvpr-vitB.pth --device cuda
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

# The node's namespace: its topics, services and diagnostics are this soak's alone, even when
# other ROS processes on this machine share the domain (one of them once cleared a soak's map).
NS = f"/vpr_soak_{os.getpid()}"

# Tiny random-network settings: only identical images pass (see test/loops/test_pipeline.py).
TINY = dict(
    global_floor=0.99999, score_threshold=-1e6, keyframe_max_similarity=0.99999, top_k=1
)  # fmt: skip


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--minutes", type=float, default=2.0, help="duration (%(default)s)")
    p.add_argument("--weights", default="random-tiny", help="checkpoint (%(default)s)")
    p.add_argument(
        "--vitb", action="store_true",
        help="random-init ViT-B/322 checkpoint written to the soak's temp folder (overrides "
        "--weights): the real model size, for timing",
    )  # fmt: skip
    p.add_argument("--precision", default="fp32", help="node precision, e.g. int8 (%(default)s)")
    p.add_argument(
        "--keyframe-interval", type=float, metavar="S",
        help="min_frame_interval S and keyframe_max_similarity 1: a keyframe every S seconds "
        "(default: the node's preset)",
    )  # fmt: skip
    p.add_argument("--budget-ms", type=float, default=0.0, help="rerank_budget_ms (%(default)s)")
    p.add_argument("--top-k", type=int, default=10, help="top_k (%(default)s)")
    p.add_argument("--queue-size", type=int, default=4, help="node queue_size (%(default)s)")
    p.add_argument("--device", default="cpu", help="node torch device (%(default)s)")
    p.add_argument("--rate", type=float, default=30.0, help="frames per second (%(default)s)")
    p.add_argument("--size", default="640x480", help="frame size WxH (%(default)s)")
    p.add_argument("--places", type=int, default=240, help="places per tour (%(default)s)")
    p.add_argument("--frames-per-place", type=int, default=6, help="(%(default)s)")
    p.add_argument("--sample", type=float, default=10.0, help="seconds per row (%(default)s)")
    p.add_argument("--warmup", type=float, default=20.0, help="s before the memory baseline")
    p.add_argument("--slack-mb", type=float, default=64.0, help="allowed non-map RSS growth")
    p.add_argument(
        "--param", action="append", default=[], metavar="NAME:=VALUE",
        help="extra node parameter (repeatable), e.g. --param precision:=int8",
    )  # fmt: skip
    p.add_argument("--out", type=Path, help="write the samples and summary as JSON here")
    p.add_argument("--plot", type=Path, help="write an RSS / map-size plot (PNG) here")
    return p.parse_args(argv)


def rss_mb(pid: int) -> float:
    """Resident memory of `pid` in MiB, from /proc/<pid>/status."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def percentiles(values: list[float]) -> str:
    if not values:
        return "n/a"
    p50, p95 = np.percentile(values, [50, 95])
    return f"p50 {p50:.1f} ms, p95 {p95:.1f} ms, max {max(values):.1f} ms (n={len(values)})"


class Camera:
    """Synthetic places: a random 60x80 texture per place, upscaled to the frame size."""

    def __init__(self, size: tuple[int, int], places: int, per_place: int) -> None:
        rng = np.random.default_rng(0)
        self.textures = rng.integers(0, 256, (places, 60, 80, 3), dtype=np.uint8)
        self.size, self.per_place = size, per_place

    def frame(self, i: int) -> bytes:
        texture = self.textures[(i // self.per_place) % len(self.textures)]
        return cv2.resize(texture, self.size, interpolation=cv2.INTER_NEAREST).tobytes()


def vitb_checkpoint(folder: Path) -> Path:
    """A random-init ViT-B/322 Pair-VPR checkpoint (the released model's shapes) in `folder`."""
    from pair_vpr_ros.model import ModelConfig, build_pairvpr
    from pair_vpr_ros.model.checkpoint import save_pairvpr

    return save_pairvpr(build_pairvpr(ModelConfig(), seed=0), folder / "vitb-random.pth")


def node_values(args: argparse.Namespace) -> dict[str, object]:
    """The node's parameters for this soak (before --param extras)."""
    values: dict[str, object] = {
        "weights": args.weights, "device": args.device, "image_topic": f"{NS}/image",
        "precision": args.precision, "queue_size": args.queue_size, "top_k": args.top_k,
        "rerank_budget_ms": args.budget_ms, "publish_rejected": True,
        "relative_pose": False,  # no camera_info: no poses; keeps SIFT out of the timings
    }  # fmt: skip
    if args.weights == "random-tiny":
        values.update(TINY)
    if args.keyframe_interval is not None:
        values.update(min_frame_interval=args.keyframe_interval, keyframe_max_similarity=1.0)
    return values


def start_node(args: argparse.Namespace, log_path: Path) -> subprocess.Popen:
    values = node_values(args)
    cmd = [sys.executable, "-m", "pair_vpr_ros.ros.node", "--ros-args"]
    cmd += ["-r", f"__ns:={NS}", "-r", f"/diagnostics:={NS}/diagnostics"]
    for name, value in values.items():
        cmd += ["-p", f"{name}:={value}"]
    for extra in args.param:
        cmd += ["-p", extra]
    log = open(log_path, "w")  # noqa: SIM115 - the node writes to it until it exits
    # Its own session: a terminal's Ctrl-C reaches the soak only, which drains and stops it.
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


class Soak:
    """The publisher / listener side; runs rclpy in this process."""

    def __init__(self, args: argparse.Namespace) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import Image
        from std_msgs.msg import String

        self.rclpy, self.Image = rclpy, Image
        rclpy.init(args=[])  # not sys.argv: rcl would read `--param a:=b` as a remap
        self.node = rclpy.create_node("vpr_soak")
        self.pub = self.node.create_publisher(Image, f"{NS}/image", qos_profile_sensor_data)
        self.diag: dict[str, str] = {}
        self.loop_ms: list[float] = []
        self.scored: list[tuple[int, int]] = []  # (candidates, scored) per record
        self.max_queue = 0
        self.node.create_subscription(String, f"{NS}/loop_closure/json", self._on_loop, 100)
        self.node.create_subscription(DiagnosticArray, f"{NS}/diagnostics", self._on_diag, 10)
        self.executor = MultiThreadedExecutor(num_threads=2)
        self.executor.add_node(self.node)
        threading.Thread(target=self.executor.spin, daemon=True).start()
        w, h = (int(v) for v in args.size.lower().split("x"))
        self.camera = Camera((w, h), args.places, args.frames_per_place)
        self.w, self.h, self.rate = w, h, args.rate
        self.published = 0
        self.stop = threading.Event()

    def now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def _on_loop(self, msg) -> None:
        record = json.loads(msg.data)
        self.loop_ms.append((self.now() - record["query_stamp"]) * 1e3)
        self.scored.append((record["candidates"], record["scored"]))

    def _on_diag(self, msg) -> None:
        for status in msg.status:
            if status.name.startswith("vpr_node"):
                self.diag = {kv.key: kv.value for kv in status.values}
                self.max_queue = max(self.max_queue, int(self.diag.get("queue_depth", 0)))

    def publish_forever(self) -> None:
        """Publish at `rate` on a fixed schedule (late frames are sent at once, not skipped)."""
        period, next_t = 1.0 / self.rate, time.monotonic()
        while not self.stop.is_set():
            data = self.camera.frame(self.published)
            msg = self.Image(height=self.h, width=self.w, encoding="rgb8", step=3 * self.w)
            msg.data = data
            msg.header.frame_id = "soak_cam"
            msg.header.stamp = self.node.get_clock().now().to_msg()
            self.pub.publish(msg)
            self.published += 1
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))

    def close(self) -> None:
        self.stop.set()
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown()


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randint(30, 99)))
    folder = Path(tempfile.mkdtemp(prefix="vpr-soak-"))
    log_path = folder / "node.log"
    if args.vitb:
        args.weights = str(vitb_checkpoint(folder))
        print(f"random-init ViT-B checkpoint {args.weights}")
    node = start_node(args, log_path)
    soak = Soak(args)
    try:
        started = time.monotonic()
        while not soak.diag:  # the node is up once it publishes diagnostics
            if node.poll() is not None or time.monotonic() - started > 600:
                print(f"error: the node did not start:\n{log_path.read_text()}", file=sys.stderr)
                return 1
            time.sleep(0.2)
        print(f"node pid {node.pid} up after {time.monotonic() - started:.1f} s; log {log_path}")
        return soak_loop(args, soak, node)
    finally:
        soak.close()
        if node.poll() is None:
            node.send_signal(signal.SIGINT)
            try:
                print(f"node exit code after SIGINT: {node.wait(60)}")
            except subprocess.TimeoutExpired:
                node.kill()
                print("error: the node did not stop within 60 s of SIGINT", file=sys.stderr)


def soak_loop(args: argparse.Namespace, soak: Soak, node: subprocess.Popen) -> int:
    threading.Thread(target=soak.publish_forever, daemon=True).start()
    t0, samples = time.monotonic(), []
    # Ctrl-C ends the run early with its summary (a KeyboardInterrupt raised while the executor
    # threads spin crashed the interpreter on shutdown).
    interrupted = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: interrupted.set())
    keys = ("frames_received", "frames_processed", "frames_dropped", "map_size", "loops",
            "queue_depth")  # fmt: skip
    print(f"{'t_s':>6} {'sent':>7} {'recv':>7} {'proc':>7} {'drop':>6} {'map':>6} {'loops':>5} "
          f"{'rss_MiB':>8} {'map_MiB':>8} {'lat_p50':>8} {'lat_p95':>8}")  # fmt: skip
    while (elapsed := time.monotonic() - t0) < args.minutes * 60 and not interrupted.is_set():
        interrupted.wait(min(args.sample, args.minutes * 60 - elapsed))
        if interrupted.is_set():
            args.minutes = (time.monotonic() - t0) / 60
            print(f"interrupted after {args.minutes:.1f} min: summary of the run so far")
        if node.poll() is not None:
            print(f"error: the node exited with {node.returncode}", file=sys.stderr)
            return 1
        d = soak.diag
        row = {"t": round(time.monotonic() - t0, 1), "published": soak.published,
               **{k: int(d.get(k, 0)) for k in keys}, "rss_mb": rss_mb(node.pid),
               "map_mb": int(d.get("map_bytes", 0)) / 2**20,
               "latency_p50": float(d.get("latency_ms_p50", "nan")),
               "latency_p95": float(d.get("latency_ms_p95", "nan"))}  # fmt: skip
        samples.append(row)
        print(f"{row['t']:6.0f} {row['published']:7d} {row['frames_received']:7d} "
              f"{row['frames_processed']:7d} {row['frames_dropped']:6d} {row['map_size']:6d} "
              f"{row['loops']:5d} {row['rss_mb']:8.1f} {row['map_mb']:8.2f} "
              f"{row['latency_p50']:8.1f} {row['latency_p95']:8.1f}")  # fmt: skip
    soak.stop.set()
    drain(soak, node)
    return summarise(args, soak, samples)


def drain(soak: Soak, node: subprocess.Popen, timeout: float = 120.0) -> None:
    """After the last frame: wait until every received frame has a fate (none queued, none in
    the worker's hands) and the counts stand still, so the summary accounts for every frame."""
    deadline, last = time.monotonic() + timeout, None
    while time.monotonic() < deadline and node.poll() is None:
        time.sleep(2.0)
        d = soak.diag
        now = tuple(d.get(k) for k in ("frames_received", "frames_processed", "queue_depth"))
        if now == last and not accounting(soak.published, d)[1]:
            return
        last = now


def accounting(published: int, d: dict[str, str]) -> tuple[dict[str, int], list[str]]:
    """Every frame's fate from the node's counters, and the identities that must hold."""
    n = {k: int(d.get(k, 0)) for k in (
        "frames_received", "frames_invalid", "frames_rate_limited", "frames_dropped",
        "frames_processed", "frames_failed", "queue_depth", "frames_encoded",
        "frames_similar_to_keyframe", "map_size")}  # fmt: skip
    gated = int(d.get("frames_rate_limited_unqueued", 0))  # never queued: counted apart
    fates = n["frames_invalid"] + gated + n["frames_dropped"] + n["frames_processed"]
    fates += n["frames_failed"] + n["queue_depth"]
    problems = []
    if fates != n["frames_received"]:
        problems.append(f"received {n['frames_received']} != sum of fates {fates}")
    if n["frames_received"] > published:
        problems.append(f"received {n['frames_received']} > published {published}")
    return {**n, "lost_before_node": published - n["frames_received"], "gated": gated}, problems


def summarise(args: argparse.Namespace, soak: Soak, samples: list[dict]) -> int:
    d = soak.diag
    base = next((s for s in samples if s["t"] >= args.warmup), samples[0])
    last = samples[-1]
    rss_growth = last["rss_mb"] - base["rss_mb"]
    map_growth = last["map_mb"] - base["map_mb"]
    bounded = rss_growth <= map_growth + args.slack_mb
    frames, problems = accounting(soak.published, d)
    # Records below the global floor score nothing (0 < k): not cut by the budget.
    cut = [(c, k) for c, k in soak.scored if args.budget_ms > 0 and 0 < k < c]
    summary = {
        "minutes": args.minutes, "weights": args.weights, "vitb": args.vitb,
        "device": args.device, "precision": args.precision, "rate_hz": args.rate,
        "keyframe_interval_s": args.keyframe_interval, "budget_ms": args.budget_ms,
        "top_k": args.top_k, "queue_size": args.queue_size, "published": soak.published,
        **frames, "accounting_problems": problems, "max_queue_depth": soak.max_queue,
        **{k: d.get(k) for k in (
            "loops", "bytes_per_keyframe", "latency_ms_p50", "latency_ms_p95", "latency_ms_max",
            "encode_ms_p50", "encode_ms_p95", "rerank_ms_p50", "rerank_ms_p95", "rerank_ms_max",
            "candidates_scored", "rerank_budget_cut", "decoder_passes", "rerank_covered",
            "rerank_skipped")},
        "records": len(soak.loop_ms), "keyframe_latency_ms": stats(soak.loop_ms),
        "records_cut_by_budget": len(cut),
        "scored_per_record": stats([float(k) for _, k in soak.scored]),
        "rss_mb_start": samples[0]["rss_mb"], "rss_mb_baseline": base["rss_mb"],
        "rss_mb_end": last["rss_mb"], "rss_mb_max": max(s["rss_mb"] for s in samples),
        "rss_growth_mb": rss_growth, "map_growth_mb": map_growth, "memory_bounded": bounded,
    }  # fmt: skip
    print("\nsummary")
    print(
        f"  frames: published {soak.published} = lost before the node "
        f"{frames['lost_before_node']} + received {frames['frames_received']}; received = "
        f"invalid {frames['frames_invalid']} + rate-limited before the queue {frames['gated']} "
        f"+ dropped (queue full) {frames['frames_dropped']} + processed "
        f"{frames['frames_processed']} + failed {frames['frames_failed']} + still queued "
        f"{frames['queue_depth']}: {'; '.join(problems) or 'every frame accounted for'}"
    )
    print(
        f"  encoded {frames['frames_encoded']}, rate-limited in all "
        f"{frames['frames_rate_limited']}, deepest queue seen {soak.max_queue} of "
        f"{args.queue_size} (diagnostics every second)"
    )
    print(
        f"  map: {d.get('map_size')} keyframes x {d.get('bytes_per_keyframe')} B, "
        f"loops {d.get('loops')}, {len(soak.loop_ms)} loop records received"
    )
    print(f"  keyframe latency (frame stamp -> its loop record): {percentiles(soak.loop_ms)}")
    print(
        f"  candidates scored per record: {summary['scored_per_record']} (top_k {args.top_k}, "
        f"budget {args.budget_ms} ms; {len(cut)} records cut by the budget)"
    )
    looked = int(d.get("rerank_covered") or 0) + int(d.get("rerank_skipped") or 0)
    summary["covered_share"] = looked / len(soak.scored) if soak.scored else None
    print(
        f"  every candidate scored at least one way, or the keyframe skipped by a floor: "
        f"{looked} of {len(soak.scored)} records; decoder passes {d.get('decoder_passes')} "
        f"(one direction of one pair each)"
    )
    print(
        f"  node, last 300 frames: latency p50 {d.get('latency_ms_p50')} / p95 "
        f"{d.get('latency_ms_p95')} / max {d.get('latency_ms_max')} ms; encode p50 "
        f"{d.get('encode_ms_p50')} ms; re-rank p50 {d.get('rerank_ms_p50')} / max "
        f"{d.get('rerank_ms_max')} ms"
    )
    print(f"  RSS: start {samples[0]['rss_mb']:.1f} MiB, at {base['t']:.0f} s "
          f"{base['rss_mb']:.1f}, end {last['rss_mb']:.1f}, max {summary['rss_mb_max']:.1f}; "
          f"growth since {base['t']:.0f} s {rss_growth:+.1f} MiB vs map growth "
          f"{map_growth:+.2f} MiB -> {'bounded' if bounded else 'NOT BOUNDED'}")  # fmt: skip
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "samples": samples}, indent=1))
    if args.plot:
        plot(samples, args.plot)
    return 0 if bounded and not problems else 2


def stats(values: list[float]) -> dict[str, float] | None:
    """p50 / p95 / max / n of `values` (None when empty)."""
    if not values:
        return None
    p50, p95 = np.percentile(values, [50, 95])
    return {"p50": float(p50), "p95": float(p95), "max": float(max(values)), "n": len(values)}


def plot(samples: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [s["t"] for s in samples]
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(t, [s["rss_mb"] for s in samples], label="node RSS (MiB)")
    ax.plot(t, [samples[0]["rss_mb"] + s["map_mb"] for s in samples], "--",
            label="start RSS + map size (MiB)")  # fmt: skip
    ax.set_xlabel("time (s)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main(argv: list[str] | None = None) -> int:
    return run(parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
