"""A `score_threshold` (and `global_floor`) chosen from one's own bag: the lowest threshold whose
loops reach a target precision against the bag's ground truth, with every stricter threshold
tried reaching it too (so noise in a score near the edge cannot take the promise away), decided
again through the detector's own code (`what_if`): temporal consistency, the sequence margin,
verification and the pose rule move with the threshold, which a raw PR curve leaves out.

`global_floor` is tried at a few values that keep nearly every revisit's global top 1 (it skips
re-ranking below it) and kept when it reaches the target at a higher recall.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.records import LoopRecord, rerank_score
from pair_vpr_ros.offline.report.decision_log import DecisionLog
from pair_vpr_ros.offline.report.loop_truth import share
from pair_vpr_ros.offline.report.what_if import StoredGeometry, WhatIf, decide_again, same_as_run
from pair_vpr_ros.params.file import yaml_text
from pair_vpr_ros.params.table import PARAMS

COARSE, FINE = 24, 12  # thresholds tried over the scores' range, then next to the best
MAX_FLOOR_ROWS = 20_000  # logs longer than this try the run's global_floor only (time)


@dataclass(frozen=True)
class Trial:
    """One setting decided again: its loops against ground truth."""

    threshold: float
    global_floor: float
    accepted: int
    true: int
    false: int
    estimated: int
    precision: float | None
    recall: float | None

    def reaches(self, target: float) -> bool:
        """Precision >= target, or no labelled loop at all (nothing wrong accepted)."""
        return self.precision is None or self.precision >= target


@dataclass
class Suggestion:
    """The chosen setting (`chosen`; None: none reached the target, `best` is the most
    precise), the run's own setting decided again (`run`) and how many keyframes that decides
    otherwise than the run did (`mismatches`, 0 when the log replays the run)."""

    target: float
    run: Trial
    mismatches: int
    chosen: Trial | None
    best: Trial
    trials: list[Trial] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        pick = self.chosen or self.best

        def trial(t: Trial) -> dict:
            return {k: getattr(t, k) for k in Trial.__dataclass_fields__}

        return {
            "target_precision": self.target, "reached": self.chosen is not None,
            "score_threshold": pick.threshold, "global_floor": pick.global_floor,
            "expected": trial(pick), "run_decided_again": trial(self.run),
            "mismatches_with_run": self.mismatches, "warnings": list(self.warnings),
        }  # fmt: skip


def _grid(values: np.ndarray, count: int) -> list[float]:
    """Up to `count` thresholds between the distinct `values`: midpoints of neighbours picked
    evenly by rank, plus one above them all."""
    distinct = np.unique(values[np.isfinite(values)])
    if len(distinct) < 2:
        return [float(v) for v in distinct]
    mids = (distinct[1:] + distinct[:-1]) / 2
    picks = np.unique(np.linspace(0, len(mids) - 1, min(count, len(mids))).round().astype(int))
    return [*(float(mids[i]) for i in picks), float(distinct[-1] + 1e-6)]


def _best_scores(log: DecisionLog, weight: float) -> np.ndarray:
    """Each keyframe's best re-rank score (what the threshold is compared with)."""
    out = np.full(len(log), -np.inf)
    for row in range(len(log)):
        lo, hi = log.start[row], log.start[row + 1]
        scores = [rerank_score(log.c_score[i], log.c_sim[i], weight) for i in range(lo, hi)]
        finite = [s for s in scores if math.isfinite(s)]
        out[row] = max(finite) if finite else -np.inf
    return out


class Search:
    """Decide the log again at thresholds and floors, count against `label` (a record ->
    True / False / None: `loop_truth.is_true_loop` with the run's ground truth)."""

    def __init__(self, log, config: DetectorConfig, geometry: StoredGeometry, identity,
                 label: Callable[[LoopRecord], bool | None], positives: int) -> None:  # fmt: skip
        self.log, self.config, self.geometry, self.identity = log, config, geometry, identity
        self.label, self.positives = label, positives
        self.tried: dict[tuple[float, float], Trial] = {}

    def trial(self, threshold: float, floor: float) -> Trial:
        key = (round(threshold, 6), floor)
        if key not in self.tried:
            again = decide_again(self.log, self.config, self.geometry, self.identity, *key)
            self.tried[key] = self._count(again)
        return self.tried[key]

    def _count(self, again: WhatIf) -> Trial:
        labels = [self.label(r) for r in again.accepted]
        true, false = labels.count(True), labels.count(False)
        precision, recall = share(true, true + false), share(true, self.positives)
        return Trial(again.threshold, again.global_floor, len(labels), true, false,
                     again.estimated, precision, recall)  # fmt: skip

    def lowest_safe(self, floor: float, grid: list[float], target: float) -> Trial | None:
        """The lowest threshold of `grid` whose trial and every higher one's reach `target`,
        among those that accept a true loop (None: none does)."""
        chosen = None
        for threshold in sorted(grid, reverse=True):
            trial = self.trial(threshold, floor)
            if not trial.reaches(target):
                break
            chosen = trial if trial.true else chosen
        return chosen


def suggest_threshold(
    log: DecisionLog,
    config: DetectorConfig,
    geometry: StoredGeometry,
    identity: tuple[str, str],
    label: Callable[[LoopRecord], bool | None],
    positives: int,
    target: float = 0.99,
) -> Suggestion:
    """Choose `score_threshold` (and `global_floor`) for precision >= `target` (module
    docstring); `positives`: keyframes with a true match (recall's denominator)."""
    search = Search(log, config, geometry, identity, label, positives)
    run = search.trial(config.score_threshold, config.global_floor)
    again = decide_again(log, config, geometry, identity, config.score_threshold)
    mismatches = same_as_run(log, again)
    best_scores = _best_scores(log, config.global_weight)
    coarse = _grid(best_scores, COARSE) + [config.score_threshold]
    floors = [config.global_floor]
    if len(log) <= MAX_FLOOR_ROWS:
        floors += _floors(log, config.global_floor)
    results = []
    for floor in floors:
        chosen = search.lowest_safe(floor, coarse, target)
        if chosen is None:
            continue
        # finer: the distinct scores between the chosen threshold and the coarse one below it
        below = [t for t in coarse if t < chosen.threshold]
        low = max(below) if below else -math.inf
        inside = best_scores[(best_scores > low) & (best_scores < chosen.threshold)]
        fine = _grid(np.append(inside, [low, chosen.threshold]), FINE)
        grid = sorted({*coarse, *(t for t in fine if math.isfinite(t))})
        results.append(search.lowest_safe(floor, grid, target) or chosen)
    chosen = max(results, key=lambda t: (t.recall or 0.0, t.global_floor == floors[0]),
                 default=None)  # fmt: skip
    trials = sorted(search.tried.values(), key=lambda t: (t.global_floor, t.threshold))
    best = max(trials, key=lambda t: (t.precision or 0.0, t.recall or 0.0))
    out = Suggestion(target, run, mismatches, chosen, best, trials)
    if mismatches:
        out.warnings.append(
            f"decided again at the run's own settings, {mismatches} keyframes came out "
            "otherwise than in the run (a re-rank budget, a map that changed): the expected "
            "figures are estimates"
        )
    if chosen is None:
        out.warnings.append(
            f"no threshold reaches precision {target:g} on this bag; the most precise one tried "
            f"is written ({_figures(best)})"
        )
    pick = chosen or best
    if pick.estimated:
        out.warnings.append(
            f"{pick.estimated} of its {pick.accepted} loops rest on a verification or pose "
            "computed from the features the map stored (the run never tried those pairs)"
        )
    return out


def _floors(log: DecisionLog, run_floor: float) -> list[float]:
    """global_floor values to try: the 2nd, 5th and 10th percentile of each keyframe's best
    global similarity (so the floor skips few keyframes), above the run's floor."""
    firsts = np.array([log.c_sim[log.start[r]] for r in range(len(log))
                       if log.start[r + 1] > log.start[r]])  # fmt: skip
    if not len(firsts):
        return []
    values = np.round(np.percentile(firsts, [2, 5, 10]), 3)
    return sorted({float(v) for v in values if v > run_floor and -1.0 <= v <= 1.0})


def _figures(t: Trial) -> str:
    def fmt(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.3f}"

    return (f"score_threshold {t.threshold:g}, global_floor {t.global_floor:g}: precision "
            f"{fmt(t.precision)}, recall {fmt(t.recall)}, {t.accepted} loops, {t.false} "
            "false")  # fmt: skip


def params_text(suggestion: Suggestion, values: dict, about: list[str]) -> str:
    """The parameter file of a suggestion: every node parameter, `values` (the run's settings)
    with the suggested `score_threshold` and `global_floor`, after a header of comment lines:
    `about` (where the figures come from), the expected figures and the warnings."""
    pick = suggestion.chosen or suggestion.best
    values = {**values, "score_threshold": float(pick.threshold),
              "global_floor": float(pick.global_floor)}  # fmt: skip
    reached = "reaches" if suggestion.chosen is not None else "does NOT reach"
    lines = [
        f"score_threshold and global_floor chosen for precision >= {suggestion.target:g}: "
        f"this setting {reached} it on the replayed bag. Expected there: {_figures(pick)}.",
        *about,
        "The other parameters are the run's. A threshold chosen on one recording is a "
        "starting point for the next: replay another recording of the robot with this file "
        "before trusting it (config/vpr_node.yaml's threshold was never chosen on data).",
        *(f"warning: {w}" for w in suggestion.warnings),
    ]
    header = [f"# {part}" for line in lines for part in textwrap.wrap(line, 97)]
    return yaml_text(PARAMS, ("# Suggested by pairvpr-bag-replay.", *header), values)
