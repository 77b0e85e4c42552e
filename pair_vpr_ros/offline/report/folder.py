"""Loop-closure report: loops CSV / JSON, ground-truth precision / recall, PR and trajectory plots.

``write_report`` writes a replay's report folder. The ground-truth rules (true match, true loop,
positives, precision, recall, PR curves) live in ``loop_truth`` and the plots in ``plots``.
"""

from __future__ import annotations

import csv
import json
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.errors import OutputError, os_reason
from pair_vpr_ros.messages.loop import LOOP_RECORD_FIELDS, csv_row, record_dict
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo, LoopEvaluation, evaluate_loops
from pair_vpr_ros.offline.report.plots import plot_pr_curves, plot_trajectory


def check_writable(path: Path, what: str) -> None:
    """`path` (a folder, created later if missing) can be written: OutputError otherwise."""
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        where = "" if existing == path else f" ({existing} is a file)"
        raise OutputError(f"{what} {path} is not a folder{where}: give a folder")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as err:
        raise OutputError(
            f"cannot write {what} {path}: {existing} is not writable ({err.strerror}); pick a "
            "writable folder"
        ) from err


@contextmanager
def writing_outputs(out: Path, what: str = "outputs") -> Iterator[None]:
    """An OSError while the block writes into `out` (a full disk, ...) -> OutputError naming
    the file when the error does (`naming`): the results are not lost to a bare traceback."""
    try:
        yield
    except OSError as err:
        file = f", writing {err.filename}" if err.filename else ""
        raise OutputError(
            f"cannot write the {what} into {out}: {os_reason(err)}{file}; free space or pick "
            "another --out"
        ) from err


@contextmanager
def naming(path: Path, partial: Path | None = None) -> Iterator[None]:
    """An OSError while the block writes `path` (through `partial`, renamed to it later) names
    `path` (a failed write() names no file); what the block wrote is removed."""
    try:
        yield
    except OSError as err:
        Path(partial or path).unlink(missing_ok=True)
        if err.filename:
            raise
        raise OSError(err.errno, err.strerror or str(err), str(path)) from err


def write_loops_csv(records: Sequence[Any], path: str | Path) -> None:
    """One row per ``LoopRecord`` (accepted or not); the header row is the field names; the
    covariance is one cell of 36 space-separated numbers."""
    with open(path, "w", newline="", encoding="utf-8") as stream:
        writer = csv.writer(stream)
        writer.writerow(LOOP_RECORD_FIELDS)
        for record in records:
            writer.writerow(csv_row(record))


def write_loops_json(records: Sequence[Any], path: str | Path) -> None:
    """A JSON list of records, each an object with every field (``loop_messages.record_dict``)."""
    Path(path).write_text(
        json.dumps([record_dict(r) for r in records], indent=1, allow_nan=False) + "\n",
        encoding="utf-8",
    )


def write_report(
    out_dir: str | Path,
    records: Sequence[Any],
    keyframes: Sequence[KeyframeInfo],
    positions: np.ndarray | None = None,
    gt_radius: float = 10.0,
    exclusion_s: float = 0.0,
    global_records: Sequence[Any] | None = None,
    source: str = "",
    global_weight: float = 0.0,
) -> LoopEvaluation | None:
    """Write ``loops.csv`` and ``loops.json``; with keyframe poses also evaluate and write
    ``pr_curve.png`` and ``trajectory.png`` (``positions [F, 3]``: every posed frame, in order;
    ``source``: where the poses come from, named in the plots' titles; ``global_weight``: the
    detector's, for the re-ranked curve's score).
    Returns the evaluation, or None without poses."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_loops_csv(records, out / "loops.csv")
    write_loops_json(records, out / "loops.json")
    if not any(k.pose is not None for k in keyframes):
        return None
    evaluation = evaluate_loops(
        records, keyframes, gt_radius, exclusion_s, global_records, global_weight
    )
    plot_pr_curves(evaluation, out / "pr_curve.png", source)
    if positions is None:
        positions = np.array([k.pose[:3] for k in keyframes if k.pose is not None])
    plot_trajectory(
        positions, keyframes, records, evaluation.labels, out / "trajectory.png", source
    )
    return evaluation
