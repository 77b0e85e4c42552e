"""What a replay writes besides loops and the map, so a person can see every decision: the report
folder (``OUT/report/``, `offline.report.html`) and the suggested parameter file
(``OUT/suggested_params.yaml``, `offline.report.suggest`)."""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.messages.loop import same_session
from pair_vpr_ros.offline.bags.pose_topics import GT_NAMES
from pair_vpr_ros.offline.report.decision_log import DecisionLog
from pair_vpr_ros.offline.report.html import PageInputs, ReportWriter, write_page
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo, KeyframeLookup, is_true_loop
from pair_vpr_ros.offline.report.suggest import params_text, suggest_threshold
from pair_vpr_ros.offline.report.what_if import StoredGeometry
from pair_vpr_ros.params.configs import defaults
from pair_vpr_ros.params.table import SPECS

SUGGESTED = "suggested_params.yaml"


def _label(keyframes: list[KeyframeInfo], gt_radius: float, exclusion_s: float):
    lookup = KeyframeLookup(keyframes)

    def label(record: LoopRecord) -> bool | None:
        if not same_session(record):
            return None
        return is_true_loop(lookup.query(record), lookup.match(record), gt_radius, exclusion_s)

    return label


def run_values(o: Any, pipe: LoopClosurePipeline, weights: str) -> dict[str, Any]:
    """The node parameters of this run: the parameter file's (`o.params_values`, else the
    defaults), with the detector and geometry settings the run used."""
    values = dict(o.params_values or defaults())
    config = asdict(pipe.config)
    values.update({k: v for k, v in config.items() if k in values})
    geometry = pipe.geometry.config
    values.update(features=geometry.features, max_features=geometry.max_features,
                  relative_pose=geometry.relative_pose)  # fmt: skip
    if weights:
        values["weights"] = weights
    return {k: float(v) if isinstance(SPECS[k].default, float) else v for k, v in values.items()}


def suggest(
    out: Path, o: Any, pipe: LoopClosurePipeline, log: DecisionLog, summary: Any,
    keyframes: list[KeyframeInfo], weights: str,
) -> dict[str, Any] | None:  # fmt: skip
    """Choose the threshold (ground truth needed) and write OUT/suggested_params.yaml."""
    ev = summary.loop_evaluation
    if ev is None or not len(log):
        return None
    start = time.perf_counter()
    geometry = StoredGeometry(pipe, log)
    identity = (pipe.identity.robot, pipe.identity.session)
    label = _label(keyframes, ev.gt_radius, ev.exclusion_s)
    found = suggest_threshold(log, pipe.config, geometry, identity, label, ev.positives,
                              o.target_precision)  # fmt: skip
    gt = summary.gt_topic or ""
    if gt.rstrip("/").rsplit("/", 1)[-1].lower() not in GT_NAMES:
        found.warnings.append(
            f"the ground truth {gt} is not named as ground truth: if it is odometry, its drift "
            "makes true loops look false (and false ones true), so the threshold may not hold; "
            "pass --gt-topic with true poses (motion capture, RTK GPS, a SLAM result)"
        )
    about = [
        f"Chosen by replaying {summary.bag} ({len(log)} keyframes) against the ground truth "
        f"{gt} (a loop is true within {ev.gt_radius:g} m, at least {ev.exclusion_s:g} s "
        f"apart; {ev.positives} keyframes have a true match), deciding every keyframe again "
        "with the detector's own code at each threshold tried.",
        f"Check: pairvpr-bag-replay {summary.bag} --params-file {out / SUGGESTED} "
        "(with the other flags of the run).",
    ]
    path = out / SUGGESTED
    path.write_text(params_text(found, run_values(o, pipe, weights), about), encoding="utf-8")
    result = found.to_dict()
    result.update(path=str(path), seconds=round(time.perf_counter() - start, 3))
    return result


def finish_report(
    report: ReportWriter, log: DecisionLog, summary: Any, keyframes: list[KeyframeInfo],
    extra: dict[str, Any], plots: list[Path],
) -> dict[str, Any]:  # fmt: skip
    """Write the report's page; -> its figures for summary.json."""
    ev = summary.loop_evaluation
    inputs = PageInputs(
        summary.to_dict(), ev, keyframes, ev.revisits if ev is not None else None,
        summary.suggestion, extra, plots,
    )  # fmt: skip
    page_s = write_page(report, log, inputs)
    folder = report.folder
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    return {
        "folder": str(folder), "index": str(folder / "index.html"), "keyframes": report.rows,
        "bytes": size, "bytes_per_keyframe": round(size / max(report.rows, 1)),
        "seconds": round(report.seconds + page_s, 3), **report.sizes(),
    }  # fmt: skip
