"""Disk, memory and time of the replay's report (OUT/report/) and decision log by keyframe count.

A synthetic run through the report's own code (no network): keyframes every 0.5 s on a 50 m
circle lapped every 60 s, each with the demo world's 320 x 240 images (cycled), `--top-k`
candidates and, for `--loops` of them, an accepted loop with 150 inlier matches and a metric
pose; then the page (labels against the circle's ground truth, index.js, index.html). Each size
runs in a fresh process and prints one Markdown row: bytes per keyframe, peak RSS, time per
keyframe while streaming, time of the page at the end.

    python benchmarks/bench_report.py --sizes 1000,10000,100000
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pair_vpr_ros.demo.render import render_frame
from pair_vpr_ros.demo.world import generate_world
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import FrameOutcome
from pair_vpr_ros.loops.records import Candidate, LoopRecord
from pair_vpr_ros.offline.replay.options import ReplaySummary
from pair_vpr_ros.offline.report.decision_log import DecisionLog
from pair_vpr_ros.offline.report.html import PageInputs, ReportWriter, write_page
from pair_vpr_ros.offline.report.loop_truth import (
    KeyframeInfo,
    LoopEvaluation,
    PRCurve,
    true_match_mask,
)

WHO = ("robot", "s1")
COV = tuple(float(v) for v in np.diag([1e-4, 1e-4, 4e-4, 1e-5, 1e-5, 1e-5]).ravel())


def outcome(i: int, k: int, loop: bool, rng: np.random.Generator) -> FrameOutcome:
    """Keyframe `i`: `k` candidates among the keyframes before it, the best accepted if `loop`."""
    out = FrameOutcome(i * 0.5, keyframe_id=i, timings_ms={"search": 1.0})
    if i < 20:
        return out
    ids = rng.choice(i - 10, size=min(k, i - 10), replace=False)
    sims = np.sort(rng.uniform(0.5, 0.95, len(ids)))[::-1]
    out.candidates = [
        Candidate(
            int(c),
            float(c) * 0.5,
            "cam",
            float(s),
            r,
            float(rng.normal(60, 10)),
            robot=WHO[0],
            session=WHO[1],
        )  # fmt: skip
        for r, (c, s) in enumerate(zip(ids, sims, strict=True), 1)
    ]
    best = out.candidates[0]
    record = LoopRecord(i, i * 0.5, "cam", best.id, best.stamp, "cam", best.pair_score,
                        best.global_similarity, 1, 1, candidates=k, scored=k, inliers=150,
                        inlier_ratio=0.6, accepted=loop, reason="" if loop else
                        "score below threshold")  # fmt: skip
    if loop:
        record.pose_status, record.pose_inliers, record.covariance = "metric", 120, COV
        record.tx, record.ty, record.tz, record.qw = 0.5, 0.0, 1.0, 1.0
        record.qx = record.qy = record.qz = 0.0
        xy = rng.uniform(0, 240, (150, 4)).astype(np.float32)
        out.matches = {1: xy}
    out.loop = record
    return out


def run_size(n: int, k: int, loops: float, keep: str | None = None) -> dict:
    world = generate_world(7, frames=60)
    images = [render_frame(world, i, (320, 240)) for i in range(0, 60, 3)]
    rng = np.random.default_rng(0)
    config = DetectorConfig(top_k=k, score_threshold=64.0, global_weight=0.0)
    with tempfile.TemporaryDirectory(prefix="bench-report-") as tmp:
        writer, log = ReportWriter(Path(tmp) / "report", config, WHO), DecisionLog()
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        start = time.perf_counter()
        for i in range(n):
            o = outcome(i, k, bool(rng.random() < loops), rng)
            row = log.add(o)
            writer.add(row, o, images[i % len(images)])
        stream_s = time.perf_counter() - start
        t = np.arange(n) * 0.5
        angle = t / 60.0 * 2 * np.pi
        xy = np.stack([50 * np.cos(angle), 50 * np.sin(angle)], axis=1)
        keyframes = [KeyframeInfo(i, float(t[i]), (*xy[i], 0.0, 0.0, 0.0, 0.0, 1.0))
                     for i in range(n)]  # fmt: skip
        revisits = true_match_mask(keyframes, 10.0, 30.0)
        empty = PRCurve(np.zeros(0), np.zeros(0), np.zeros(0))
        ev = LoopEvaluation(10.0, 30.0, int(revisits.sum()), [], 0, 0, 0, 0, empty, None,
                            revisits=revisits)  # fmt: skip
        summary = ReplaySummary("synthetic", "/cam", None).to_dict()
        page_s = write_page(writer, log, PageInputs(summary, ev, keyframes, revisits))
        size = sum(p.stat().st_size for p in (Path(tmp) / "report").rglob("*") if p.is_file())
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        if keep:
            shutil.copytree(Path(tmp) / "report", Path(keep) / f"report-{n}", dirs_exist_ok=True)
    return {"keyframes": n, "bytes_per_keyframe": round(size / n), "total_mb": size / 1e6,
            "stream_ms_per_keyframe": 1e3 * stream_s / n, "page_s": page_s,
            "rss_mb": rss / 1024, "rss_growth_mb": (rss - rss0) / 1024}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="1000,10000", help="keyframe counts, comma-separated")
    p.add_argument("--top-k", type=int, default=5, help="candidates per keyframe (default 5)")
    p.add_argument("--loops", type=float, default=0.5, help="share of keyframes with a loop")
    p.add_argument("--keep", metavar="DIR", help="copy each size's report to DIR/report-N")
    p.add_argument("--one", type=int, help=argparse.SUPPRESS)  # a child process: one size
    args = p.parse_args()
    if args.one is not None:
        print(json.dumps(run_size(args.one, args.top_k, args.loops, args.keep)))
        return
    print("| keyframes | bytes / keyframe | total MB | streaming ms / keyframe | page s | "
          "peak RSS MB (growth) |\n|---|---|---|---|---|---|")  # fmt: skip
    for n in (int(v) for v in args.sizes.split(",")):
        keep = ["--keep", args.keep] if args.keep else []
        cmd = [sys.executable, __file__, "--one", str(n), "--top-k", str(args.top_k),
               "--loops", str(args.loops), *keep]  # fmt: skip
        r = json.loads(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)
        print(f"| {n:,} | {r['bytes_per_keyframe']:,} | {r['total_mb']:.0f} | "
              f"{r['stream_ms_per_keyframe']:.2f} | {r['page_s']:.2f} | {r['rss_mb']:.0f} "
              f"({r['rss_growth_mb']:.0f}) |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
