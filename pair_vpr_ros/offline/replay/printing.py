"""What `pairvpr-bag-replay` prints when a replay is over: warnings (stderr), precision and
recall, the prior maps' loops, the suggested threshold and where the outputs are."""

from __future__ import annotations

import sys
from typing import Any


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def print_results(summary: Any) -> None:
    """Print a `ReplaySummary`'s results (all but its last line, `summary.line()`)."""
    for warning in summary.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    ev, prior = summary.evaluation, summary.prior_evaluation
    if ev is not None:
        print(
            f"{'live loops: ' if summary.prior_maps else ''}"
            f"precision {_fmt(ev['precision'])}, recall {_fmt(ev['recall'])} "
            f"({ev['positives']} keyframes with a true match within {ev['gt_radius_m']} m; "
            f"ground truth {ev['gt_topic']})"
        )
    if prior is not None:
        print(
            f"prior-map loops: {prior['accepted']} ({prior['true_accepted']} true, "
            f"{prior['false_accepted']} false, {prior['unlabelled_accepted']} unlabelled: "
            f"{prior['covered']} of {prior['prior_keyframes']} prior keyframes have ground "
            f"truth), precision {_fmt(prior['precision'])}, recall {_fmt(prior['recall'])} "
            f"({prior['positives']} keyframes with a prior keyframe within "
            f"{prior['gt_radius']} m)"
        )
    if summary.suggestion is not None:
        _print_suggestion(summary.suggestion)
    if summary.report is not None:
        print(f"report: {summary.report['index']} (open it in a browser)")
    print(f"outputs in {summary.out_dir}")


def _print_suggestion(s: dict) -> None:
    e = s["expected"]
    reached = "reaches" if s["reached"] else "does NOT reach"
    print(
        f"suggested score_threshold {s['score_threshold']:g} (global_floor "
        f"{s['global_floor']:g}) {reached} precision {s['target_precision']:g} on this bag: "
        f"expected precision {_fmt(e['precision'])}, recall {_fmt(e['recall'])} "
        f"({e['accepted']} loops, {e['false']} false); written to {s['path']}"
        + (f" ({len(s['warnings'])} warnings in it)" if s["warnings"] else "")
    )
