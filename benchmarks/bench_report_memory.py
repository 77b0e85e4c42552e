"""Memory and time of the end-of-replay report (ground truth, PR curves, plots) by keyframe count.

A synthetic run: keyframes every 0.5 s on a 50 m circle lapped every 60 s (so most keyframes
have true matches), one loop record per keyframe, half of them accepted. Each size runs in a
fresh process; the peak of Python + numpy allocations (tracemalloc) and the process's peak RSS
are printed as a Markdown table, per part: `gt` (queries_with_true_match), `evaluate`
(evaluate_loops with the global-only curve) and `report` (write_report: CSV, JSON, both plots).

    python benchmarks/bench_report_memory.py --sizes 600,5000,20000
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc

import numpy as np

from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.offline.report import folder as report
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo, queries_with_true_match

PARTS = ("gt", "evaluate", "report")


def synthetic_run(n: int) -> tuple[list[KeyframeInfo], list[LoopRecord], np.ndarray]:
    rng = np.random.default_rng(0)
    t = np.arange(n) * 0.5
    angle = t / 60.0 * 2 * np.pi
    xyz = np.stack([50 * np.cos(angle), 50 * np.sin(angle), np.zeros(n)], axis=1)
    xyz += rng.normal(0.0, 0.5, (n, 3))
    keyframes = [KeyframeInfo(i, float(t[i]), (*xyz[i], 0.0, 0.0, 0.0, 1.0)) for i in range(n)]
    records = []
    for i in range(1, n):
        m = int(rng.integers(0, i))
        records.append(
            LoopRecord(
                i,
                float(t[i]),
                "cam",
                m,
                float(t[m]),
                "cam",
                float(rng.normal()),
                float(rng.random()),
                1,
                1,
                accepted=bool(rng.random() < 0.5),
            )  # fmt: skip
        )
    return keyframes, records, xyz


def measure(n: int, part: str) -> dict:
    keyframes, records, xyz = synthetic_run(n)
    tracemalloc.start()
    start = time.perf_counter()
    if part == "gt":
        queries_with_true_match(keyframes, 10.0, 30.0)
    elif part == "evaluate":
        report.evaluate_loops(records, keyframes, 10.0, 30.0, records)
    else:
        with tempfile.TemporaryDirectory() as out:
            report.write_report(out, records, keyframes, xyz, 10.0, 30.0, records)
    seconds = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1]
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"n": n, "part": part, "traced_mib": peak / 2**20, "rss_mib": rss, "s": seconds}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="600,5000", help="keyframe counts (default: %(default)s)")
    p.add_argument("--one", nargs=2, metavar=("N", "PART"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one:
        print(json.dumps(measure(int(args.one[0]), args.one[1])))
        return
    print("| keyframes | part | peak allocations (MiB) | peak RSS (MiB) | seconds |")
    print("|---|---|---|---|---|")
    for n in (int(float(s)) for s in args.sizes.split(",")):
        for part in PARTS:
            cmd = [sys.executable, __file__, "--one", str(n), part]
            row = json.loads(subprocess.run(cmd, check=True, capture_output=True).stdout)
            print(
                f"| {n} | {part} | {row['traced_mib']:.1f} | {row['rss_mib']:.0f} | "
                f"{row['s']:.2f} |"
            )


if __name__ == "__main__":
    main()
