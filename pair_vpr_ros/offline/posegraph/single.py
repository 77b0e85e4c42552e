"""One robot's recorded odometry + the loops of a replay -> the optimised trajectory.

The library behind `pairvpr-posegraph BAG --loops ...` (cli.py parses the flags); the fleet
form, several robot-sessions in one graph, is fleet.py.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.errors import ConfigError, PoseGraphError
from pair_vpr_ros.messages.factor import LoopFactor
from pair_vpr_ros.offline.bags import reader as bag_io
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.report.folder import writing_outputs
from pair_vpr_ros.offline.report.loop_io import read_loops
from pair_vpr_ros.offline.report.trajectories import (
    Trajectory,
    plot_trajectories,
    trajectory_errors,
    write_tum,
)
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.graph import PoseGraph
from pair_vpr_ros.posegraph.simulate import false_loops


@dataclass
class PoseGraphSummary:
    """What one run did; ``errors`` holds ATE / RPE (m) when there is ground truth."""

    odometry_messages: int = 0
    nodes: int = 0
    loops_source: str = ""  # what the loops file held (loop_io.LoopSource.line)
    loops_read: int = 0  # loops with a relative pose
    loops_injected_false: int = 0
    loops_added: int = 0
    # Loops whose residual is above the chi-square 99 % bound at the end: the robust kernel has
    # down-weighted them (false loops, and true ones whose covariance is too confident).
    loop_outliers: int = 0
    injected_false_outliers: int = 0
    odometry_gaps: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    update_ms_mean: float = 0.0
    update_ms_max: float = 0.0
    errors: dict[str, Any] = field(default_factory=dict)  # {"odometry": ..., "optimised": ...}
    config: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    out_dir: str = ""

    def ate_line(self) -> str | None:
        """``drift (ATE RMSE) odometry 3.41 m -> optimised 0.32 m (0.09x)``, or None."""
        if "odometry" not in self.errors or "optimised" not in self.errors:
            return None
        before = self.errors["odometry"]["ate_rmse"]
        after = self.errors["optimised"]["ate_rmse"]
        ratio = after / before if before > 0 else float("nan")
        return (
            f"drift (ATE RMSE) odometry {before:.3f} m -> optimised {after:.3f} m ({ratio:.2f}x)"
        )


def optimise(
    odometry: Trajectory, loops: list[LoopFactor], config: PoseGraphConfig | None = None
) -> tuple[PoseGraph, np.ndarray]:
    """Feed ``odometry`` and ``loops`` in stamp order into a ``PoseGraph`` (updated after each
    odometry message, as the node does); returns the graph and the update times ``[U]`` s."""
    graph = PoseGraph(config)
    order = sorted(loops, key=lambda lp: lp.query_stamp)
    times = []
    k = 0
    for stamp, pose in zip(odometry.stamps, odometry.poses, strict=True):
        graph.add_odometry(float(stamp), tuple(pose))
        while k < len(order) and order[k].query_stamp <= stamp:
            graph.add_loop(order[k])
            k += 1
        start = time.perf_counter()
        if graph.update():
            times.append(time.perf_counter() - start)
    for loop in order[k:]:
        graph.add_loop(loop)
    graph.finish()
    return graph, np.asarray(times, dtype=np.float64)


def read_track(reader: Any, topic: str, what: str, summary: PoseGraphSummary) -> Trajectory:
    """The poses of ``topic`` as a trajectory; a topic without poses is a ``PoseGraphError``.
    Poses with NaN / inf values (left out by ``read_poses``) are counted in ``summary``."""
    track, error = bag_io.read_poses(reader, bag_io.choose_pose_topic(reader, topic))
    if error is not None:
        summary.warnings.append(error)
    if track.rejected:
        key = f"{what}: pose has NaN or infinite values"
        summary.skipped[key] = summary.skipped.get(key, 0) + track.rejected
    if len(track) == 0:
        raise PoseGraphError(
            f"{what} topic {topic} has no messages" + (f" ({error})" if error else "")
        )
    stamps, poses = track.items()
    return Trajectory(np.asarray(stamps, dtype=np.float64), np.asarray(poses, dtype=np.float64))


def _graph_trajectories(graph: PoseGraph) -> tuple[Trajectory, Trajectory]:
    stamps = graph.node_stamps()
    return Trajectory(stamps, graph.odometry_poses()), Trajectory(stamps, graph.optimised_poses())


def run_posegraph(
    bag: str | Path,
    loops_path: str | Path,
    out_dir: str | Path = "posegraph_out",
    odom_topic: str = "/odom",
    gt_topic: str | None = None,
    config: PoseGraphConfig | None = None,
    false_loop_fraction: float = 0.0,
    seed: int = 0,
) -> PoseGraphSummary:
    """Odometry of ``odom_topic`` in ``bag`` + the loops at ``loops_path`` (``loop_io``) -> files
    in ``out_dir`` (see the module docstring). ``false_loop_fraction`` adds that many wrong loops
    per real one (seeded; needs ``gt_topic``) to test robustness. Raises ``PairVPRError``
    subclasses for unusable input."""
    config = config or PoseGraphConfig()
    config.validate()
    if not 0.0 <= false_loop_fraction <= 10.0:
        raise ConfigError(f"false-loop fraction {false_loop_fraction} must be within 0-10")
    if false_loop_fraction > 0 and gt_topic is None:
        raise ConfigError("injecting false loops needs ground truth: pass --gt-topic")
    summary = PoseGraphSummary(config=asdict(config))
    with open_bag(bag) as reader:
        odometry = read_track(reader, odom_topic, "odometry", summary)
        truth = read_track(reader, gt_topic, "ground-truth", summary) if gt_topic else None
    source = read_loops(loops_path)
    unusable = summary.skipped.get("odometry: pose has NaN or infinite values", 0)
    summary.odometry_messages, summary.loops_read = len(odometry) + unusable, len(source.factors)
    summary.loops_source = source.line()
    if not source.factors:
        summary.warnings.append(
            f"no loop closure with a relative pose in {loops_path} ({source.line()}): the "
            "optimised trajectory is the odometry"
        )
    injected: list[LoopFactor] = []
    if truth is not None and false_loop_fraction > 0:
        count = int(round(false_loop_fraction * len(source.factors)))
        injected = false_loops(truth.stamps, truth.poses, count, np.random.default_rng(seed),
                               camera_to_base=config.camera_to_base)  # fmt: skip
    graph, times = optimise(odometry, source.factors + injected, config)
    _summarise(summary, graph, times, injected)
    with writing_outputs(Path(out_dir), "pose graph's outputs"):
        _write_outputs(Path(out_dir), summary, graph, truth)
    return summary


def _write_outputs(
    out: Path, summary: PoseGraphSummary, graph: PoseGraph, truth: Trajectory | None
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    summary.out_dir = str(out)
    before, after = _graph_trajectories(graph)
    write_tum(out / "odometry.tum", before)
    write_tum(out / "optimised.tum", after)
    (out / "ground_truth.tum").unlink(missing_ok=True)  # an earlier run's would mislead
    if truth is not None:
        write_tum(out / "ground_truth.tum", truth)
        for name, estimate in (("odometry", before), ("optimised", after)):
            summary.errors[name] = trajectory_errors(estimate, truth).to_dict()
    plot_trajectories(out / "posegraph.png", truth, before, after, graph.loop_segments(),
                      graph.loop_inliers(), summary.ate_line() or "")  # fmt: skip
    (out / "posegraph.json").write_text(json.dumps(asdict(summary), indent=1) + "\n")


def _summarise(
    summary: PoseGraphSummary, graph: PoseGraph, times: np.ndarray, injected: list[LoopFactor]
) -> None:
    counts = graph.counts
    inliers = graph.loop_inliers()
    false = np.array([any(e.factor is f for f in injected) for e in graph.loops], dtype=bool)
    summary.loops_injected_false = len(injected)
    summary.nodes = counts.nodes
    summary.loops_added = counts.loops_added
    summary.loop_outliers = int((~inliers).sum())
    summary.injected_false_outliers = int((~inliers & false).sum())
    summary.odometry_gaps = counts.odometry_gaps
    for reason, n in counts.skipped.items():  # after the poses read_poses left out
        summary.skipped[reason] = summary.skipped.get(reason, 0) + n
    if len(times):
        summary.update_ms_mean = float(times.mean() * 1e3)
        summary.update_ms_max = float(times.max() * 1e3)
