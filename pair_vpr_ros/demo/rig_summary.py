"""`make demo-rig`'s table (issue 49): the rig world replayed with the front camera alone and
with front + rear, each corrected by the pose graph, side by side in ``rig_summary.json``.

For each run (``front_only``, ``rig``): ``opposite_recall`` (the revisits driven the other way
round that got a true loop: ``offline.report.directions``), ``same_recall``, ``precision`` and
``recall`` of the accepted loops, the loops and posed loops, and ``ate_m`` (ATE RMSE of the
optimised trajectory against ground truth; ``ate_odometry_m`` the odometry's). ``targets``
says which of the issue's targets the figures meet.

    python -m pair_vpr_ros.demo.rig_summary demo_out/rig
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from pair_vpr_ros.cli import run_cli
from pair_vpr_ros.errors import UsageError

RUNS = ("front_only", "rig")


def _read(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:
        raise UsageError(f"cannot read {path} ({err}): run make demo-rig first") from err


def run_figures(folder: Path, name: str) -> dict[str, Any]:
    """One run's figures from its replay's summary.json and its pose graph's posegraph.json."""
    replay = _read(folder / name / "summary.json")
    graph = _read(folder / f"{name}_posegraph" / "posegraph.json")
    ev, directions = replay.get("evaluation") or {}, replay.get("directions") or {}
    counts = replay.get("pipeline_counts", {})
    return {
        "opposite_recall": (directions.get("opposite") or {}).get("recall"),
        "opposite_revisits": (directions.get("opposite") or {}).get("positives"),
        "same_recall": (directions.get("same") or {}).get("recall"),
        "precision": ev.get("precision"),
        "recall": ev.get("recall"),
        "loops": replay.get("loops"),
        "posed_loops": counts.get("pose_metric", 0) + counts.get("pose_metric_odometry", 0),
        "ate_m": graph["errors"]["optimised"]["ate_rmse"],
        "ate_odometry_m": graph["errors"]["odometry"]["ate_rmse"],
        "cameras": [c["name"] for c in (replay.get("rig") or {}).get("cameras", [])] or ["front"],
    }


def rig_summary(folder: str | Path) -> dict[str, Any]:
    """Both runs' figures and the targets they meet; writes ``folder/rig_summary.json``."""
    folder = Path(folder)
    out: dict[str, Any] = {name: run_figures(folder, name) for name in RUNS}
    front, rig = out["front_only"], out["rig"]
    out["targets"] = {
        "rig opposite_recall >= 0.8": (rig["opposite_recall"] or 0.0) >= 0.8,
        "rig precision >= 0.98": (rig["precision"] or 0.0) >= 0.98,
        "rig ate_m <= front_only ate_m": rig["ate_m"] <= front["ate_m"],
    }
    (folder / "rig_summary.json").write_text(json.dumps(out, indent=1) + "\n")
    return out


def table(summary: dict[str, Any]) -> str:
    """The two runs as a text table (what make demo-rig prints)."""

    def cell(value: Any, fmt: str = ".3f") -> str:
        return "n/a" if value is None else format(value, fmt)

    rows = ["run         opposite recall  same recall  precision  loops  posed  ATE (m)"]
    for name in RUNS:
        r = summary[name]
        rows.append(
            f"{name:<11} {cell(r['opposite_recall']):>15}  {cell(r['same_recall']):>11}  "
            f"{cell(r['precision']):>9}  {r['loops']:>5}  {r['posed_loops']:>5}  "
            f"{cell(r['ate_m'])} (odometry {cell(r['ate_odometry_m'])})"
        )
    met = [f"{k}: {'met' if ok else 'NOT met'}" for k, ok in summary["targets"].items()]
    return "\n".join([*rows, "targets: " + "; ".join(met)])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m pair_vpr_ros.demo.rig_summary",
        description="Compare make demo-rig's two runs (front camera alone, front + rear) and "
        "write FOLDER/rig_summary.json.",
    )
    parser.add_argument(
        "folder", type=Path, help="make demo-rig's output folder (demo_out/rig): front_only/, "
        "rig/ and their *_posegraph/ folders",
    )  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    """Exit codes: `pair_vpr_ros.cli`."""
    return run_cli(build_parser(), lambda args: print(table(rig_summary(args.folder))), argv)


if __name__ == "__main__":
    sys.exit(main())
