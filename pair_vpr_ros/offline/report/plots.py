"""The report's PNG plots (matplotlib, Agg backend): PR curves and the path with its loops."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.messages.loop import same_session
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo, KeyframeLookup, LoopEvaluation

TARGETS = (0.99, 0.95, 0.90)  # precisions whose thresholds the PR plot and the report list


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")  # files only: never open a window, also on machines with a display
    import matplotlib.pyplot as plt

    return plt


def plot_pr_curves(
    evaluation: LoopEvaluation, path: str | Path, source: str = "", threshold: float | None = None
) -> None:
    """PNG of the re-ranked (and global-only) PR curves with the run's operating point, the
    curve's points at ``threshold`` (the run's) and the thresholds that reach precision 0.99 /
    0.95 / 0.90; ``source`` names the ground truth in the title."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    curves = [("re-ranked", evaluation.reranked, "tab:blue")]
    if evaluation.global_only is not None:
        curves.append(("global only (similarity)", evaluation.global_only, "tab:orange"))
    for label, curve, color in curves:
        ap = curve.average_precision()
        ax.step(
            curve.recall, curve.precision, where="post", color=color, label=f"{label}, AP {ap:.3f}"
        )
    curve = evaluation.reranked
    for target, marker in zip(TARGETS, "^sD", strict=True):
        point = curve.operating_point(target)
        if point is not None:
            ax.plot(point[2], point[1], marker, color="tab:blue", mfc="white", ms=7,
                    label=f"precision >= {target:g}: threshold {point[0]:.4g}")  # fmt: skip
    at = curve.at_threshold(threshold) if threshold is not None else None
    if at is not None:
        ax.plot(at[1], at[0], "x", color="k", ms=9, mew=2,
                label=f"the run's threshold {threshold:g} on the curve")  # fmt: skip
    if evaluation.precision is not None and evaluation.recall is not None:
        ax.plot(evaluation.recall, evaluation.precision, "k*", ms=11, label="accepted loops")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.02), ylim=(0, 1.05))
    title = f"loop closures, {evaluation.positives} queries with a true match"
    ax.set_title(title + (f"\nground truth: {source}" if source else ""), fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_trajectory(
    positions: np.ndarray,
    keyframes: Sequence[KeyframeInfo],
    records: Sequence[Any],
    labels: Sequence[bool | None],
    path: str | Path,
    source: str = "",
    missed: np.ndarray | None = None,
) -> None:
    """PNG of the x/y path ``positions [F, 2+]``, keyframes, and accepted loops (green true,
    red false, grey unlabelled) drawn between their two keyframes (a dot when they coincide),
    ``missed`` revisits [M, 2+] (keyframes with a true match and no true loop) as orange
    crosses; ``source`` names the ground truth the positions come from in the title."""
    plt = _pyplot()
    from matplotlib.collections import LineCollection

    lookup = KeyframeLookup(keyframes)
    by_id = {k.id: k.pose for k in keyframes if k.pose is not None and k.stored}
    fig, ax = plt.subplots(figsize=(6, 6))
    if len(positions):
        ax.plot(positions[:, 0], positions[:, 1], "-", color="0.6", lw=1, label="path")
    if by_id:
        xy = np.array([pose[:2] for pose in by_id.values()])
        ax.plot(xy[:, 0], xy[:, 1], ".", color="tab:blue", ms=4, label="keyframes")
    colors = {True: "tab:green", False: "tab:red", None: "0.4"}
    names = {True: "true loop", False: "false loop", None: "loop (no pose)"}
    segments: dict[bool | None, list] = {True: [], False: [], None: []}
    for record, label in zip(records, labels, strict=True):
        q, m = (getattr(lookup.query(record), "pose", None), by_id.get(record.match_id))
        if record.accepted and q is not None and m is not None and same_session(record):
            segments[label].append(((q[0], q[1]), (m[0], m[1])))
    for label, lines in segments.items():  # one artist per kind: thousands of loops stay cheap
        if lines:
            ends = np.asarray(lines, dtype=np.float64).reshape(-1, 2)
            ax.add_collection(LineCollection(lines, colors=colors[label], linewidths=1.5))
            ax.plot(ends[:, 0], ends[:, 1], "o", color=colors[label], ms=4, label=names[label])
    if missed is not None and len(missed):
        ax.plot(missed[:, 0], missed[:, 1], "x", color="tab:orange", ms=6, mew=1.5,
                label=f"missed revisit ({len(missed)})")  # fmt: skip
    ax.set(xlabel="x [m]", ylabel="y [m]", aspect="equal")
    if source:
        ax.set_title(f"path and loops, ground truth: {source}", fontsize=10)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
