"""``index.html`` and ``index.js`` of a replay's report, written when the replay is over: the
summary, the settings that decide, the warnings, the PR curve's operating points (the thresholds
that reach precision 0.99 / 0.95 / 0.90, re-ranked and global only), the suggested threshold,
the plots, and the table's script, which pages through the rows the writer streamed. Jinja2
templates in ``templates/``; the script and style go inline, so the folder needs nothing else.
"""

from __future__ import annotations

import math
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import jinja2
import markupsafe

from pair_vpr_ros.errors import OutputError
from pair_vpr_ros.offline.report.decision_log import DecisionLog
from pair_vpr_ros.offline.report.html.labels import row_labels, write_index
from pair_vpr_ros.offline.report.html.writer import CHUNK, ReportWriter
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo, LoopEvaluation, PRCurve
from pair_vpr_ros.offline.report.plots import TARGETS

TEMPLATES = Path(__file__).with_name("templates")
# inline in the page (the folder then needs no other file to show it)
ASSETS = {"style": "report.css", "bootstrap": "bootstrap.js", "script": "report.js"}
# the settings that decide, in the order a reader checks them
SETTINGS = ("top_k", "score_threshold", "global_weight", "global_floor", "sequence_margin",
            "temporal_consistency", "temporal_tolerance", "geometric_verification",
            "min_inliers", "exclude_recent_s", "exclude_recent_keyframes", "rerank_budget_ms",
            "keyframe_max_similarity", "min_frame_interval", "map_growth", "mode",
            "loop_per_map")  # fmt: skip


@dataclass
class PageInputs:
    """What the page shows besides the rows: `summary` (summary.json's dict), `evaluation`
    (None without ground truth), the keyframes it labels, `revisits` (which of them have a true
    match), `suggestion` (its dict or None), `extra` settings (index, codec, features), the
    plots to copy into the folder."""

    summary: dict[str, Any]
    evaluation: LoopEvaluation | None = None
    keyframes: Sequence[KeyframeInfo] = ()
    revisits: Any = None
    suggestion: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    plots: Sequence[Path] = ()


def _point(curve: PRCurve | None, precision: float) -> dict | None:
    point = curve.operating_point(precision) if curve is not None else None
    if point is None:
        return None
    return {"threshold": point[0], "precision": point[1], "recall": point[2]}


def _at_threshold(curve: PRCurve, threshold: float) -> dict | None:
    """The curve's precision and recall when accepting every score >= `threshold`."""
    point = curve.at_threshold(threshold)
    if point is None:
        return None
    return {"threshold": threshold, "precision": point[0], "recall": point[1]}


def curve_points(evaluation: LoopEvaluation | None, threshold: float) -> dict[str, Any]:
    """The operating points the page lists (empty without ground truth)."""
    if evaluation is None:
        return {}
    return {
        "targets": [
            {
                "precision": p,
                "reranked": _point(evaluation.reranked, p),
                "global": _point(evaluation.global_only, p),
            }  # fmt: skip
            for p in TARGETS
        ],
        "current": _at_threshold(evaluation.reranked, threshold),
        "ap": evaluation.reranked.average_precision(),
        "ap_global": evaluation.global_only.average_precision()
        if evaluation.global_only is not None
        else None,
    }


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.{digits}f}" if math.isfinite(value) else "n/a"
    return str(value)


def render(context: dict[str, Any]) -> str:
    loader = jinja2.FileSystemLoader(TEMPLATES)
    env = jinja2.Environment(loader=loader, autoescape=True, undefined=jinja2.StrictUndefined)
    env.filters["fmt"] = _fmt
    return env.get_template("report.html.j2").render(**context)


def write_page(writer: ReportWriter, log: DecisionLog, inputs: PageInputs) -> float:
    """Write the last rows, label them, write index.js and index.html, copy the plots; ->
    seconds spent (besides the writer's own, `writer.seconds`)."""
    writer.close_rows()
    start = time.perf_counter()
    folder = writer.folder
    ev, summary = inputs.evaluation, inputs.summary
    gt = (ev.gt_radius, ev.exclusion_s) if ev is not None else (0.0, 0.0)
    flags, labels = row_labels(log, writer.flags, writer.identity, inputs.keyframes,
                               inputs.revisits if ev is not None else None, *gt)  # fmt: skip
    config = summary.get("config", {})
    context = {
        "title": Path(summary.get("bag", "replay")).name,
        "written": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "summary": summary,
        "settings": {k: config[k] for k in SETTINGS if k in config} | inputs.extra,
        "evaluation": summary.get("evaluation"),
        "points": curve_points(ev, config.get("score_threshold", 0.0)),
        "suggestion": inputs.suggestion,
        "plots": [p.name for p in inputs.plots if p.is_file()],
        "rows": len(flags),
        "config": {"weight": config.get("global_weight", 0.0), "truth": ev is not None},
        **{name: markupsafe.Markup((TEMPLATES / file).read_text(encoding="utf-8"))
           for name, file in ASSETS.items()},
    }  # fmt: skip
    try:
        write_index(folder, flags, labels, CHUNK)
        for plot in context["plots"]:
            shutil.copyfile(next(p for p in inputs.plots if p.name == plot), folder / plot)
        (folder / "index.html").write_text(render(context), encoding="utf-8")
    except OSError as err:
        raise OutputError(f"cannot write the report into {folder}: {err}") from err
    return time.perf_counter() - start
