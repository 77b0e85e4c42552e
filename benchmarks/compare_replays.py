"""Compare two demo runs (issue 34: a dense codec against float16): re-ranked top-1 by keyframe id.

Each run is the OUT folder of `scripts/demo.sh` (OUT/replay/loops.json, OUT/replay/summary.json,
OUT/posegraph/posegraph.json), e.g. one made with `dense_codec: f16` in a copy of
config/demo.yaml and one with the codec under test. Reported: the queries whose re-ranked top-1
(`match_id` of each queried keyframe's record, accepted or not) is the same keyframe in both
runs, the queries decided the same way (accepted or not), and per run the loops accepted, the
loops with a metric pose, the re-ranked AP and the pose graph's ATE RMSE. Targets (issue 34):
top-1 agreement >= 99 %, AP within 0.005, posed loops within 2 %, ATE within 0.01 m.

    python benchmarks/compare_replays.py /var/tmp/x/demo-f16 /var/tmp/x/demo-p4
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def figures(out: Path) -> dict:
    """-> {"top1": {query_id: match_id}, "accepted": {query_id: bool}, and the run's totals}."""
    records = json.loads((out / "replay" / "loops.json").read_text())
    summary = json.loads((out / "replay" / "summary.json").read_text())
    graph = out / "posegraph" / "posegraph.json"
    ate = (
        json.loads(graph.read_text())["errors"]["optimised"]["ate_rmse"]
        if graph.is_file()
        else None
    )
    return {
        "top1": {r["query_id"]: r["match_id"] for r in records},
        "accepted": {r["query_id"]: bool(r["accepted"]) for r in records},
        "loops": summary["loops"],
        "posed": summary["pipeline_counts"]["pose_metric"],
        "ap": summary["evaluation"]["reranked"]["average_precision"],
        "precision": summary["evaluation"]["precision"],
        "recall": summary["evaluation"]["recall"],
        "ate": ate,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("reference", type=Path, help="OUT of the reference run (float16 tokens)")
    p.add_argument("other", type=Path, help="OUT of the run to compare")
    args = p.parse_args(argv)
    ref, other = figures(args.reference), figures(args.other)
    shared = sorted(set(ref["top1"]) & set(other["top1"]))
    differ = [q for q in shared if ref["top1"][q] != other["top1"][q]]
    decided = sum(ref["accepted"][q] == other["accepted"][q] for q in shared)
    print(f"queries in both runs: {len(shared)} (reference {len(ref['top1'])}, other "
          f"{len(other['top1'])})")  # fmt: skip
    print(f"re-ranked top-1 the same keyframe: {len(shared) - len(differ)} of {len(shared)} "
          f"({(len(shared) - len(differ)) / max(len(shared), 1):.4f}); decided the same way: "
          f"{decided}")  # fmt: skip
    for q in differ:
        print(f"  query {q}: reference's top-1 {ref['top1'][q]}, other's {other['top1'][q]}")
    for name, f in (("reference", ref), ("other", other)):
        ate = "-" if f["ate"] is None else f"{f['ate']:.3f} m"
        print(f"{name}: {f['loops']} loops, precision {f['precision']:.3f} / recall "
              f"{f['recall']:.3f}, {f['posed']} posed, re-ranked AP {f['ap']:.5f}, "
              f"ATE {ate}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
