"""`pairvpr-posegraph --trajectory ...`: several robot-sessions in one pose graph.

Each ``--trajectory ROBOT SESSION BAG`` gives one robot-session's odometry (and ground truth);
the loops of every ``--loops`` source are placed between the trajectories their
``query_robot/query_session`` and ``match_robot/match_session`` name (a replay run with
``--robot-id``/``--session-id`` writes them). The first trajectory is the map frame; the others
join it once their loops agree on where they are (``posegraph.joining``). Writes into ``--out``:

``<robot>/<session>/odometry.tum``, ``optimised.tum`` (``ground_truth.tum`` with ``--gt-topic``)
    per robot-session: odometry in its own frame, optimised poses in the first one's frame;
``posegraph.json``
    per trajectory: messages, nodes, joined or not, ATE / RPE before and after (each SE(3)-aligned
    to its ground truth) and ``ate_in_reference_frame``: the ATE after moving it by the first
    trajectory's alignment only (all in one frame: each within a metre when it works);
``posegraph.png``
    before (odometry, each in its own frame) and after (optimised, map frame) with the loops.
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.errors import ConfigError, PairVPRError, UsageError
from pair_vpr_ros.identity import name_problem
from pair_vpr_ros.messages.factor import LoopFactor
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.posegraph.single import PoseGraphSummary, read_track
from pair_vpr_ros.offline.report.folder import writing_outputs
from pair_vpr_ros.offline.report.loop_io import read_loops
from pair_vpr_ros.offline.report.trajectories import (
    Trajectory,
    plot_fleet,
    reference_alignment,
    trajectory_errors,
    write_tum,
)
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.graph import PoseGraph
from pair_vpr_ros.posegraph.loops import own
from pair_vpr_ros.posegraph.tracks import TrajectoryId, label


@dataclass(frozen=True)
class TrajectoryInput:
    """One ``--trajectory``: the robot-session and the bag with its odometry."""

    robot: str
    session: str
    bag: Path

    @property
    def id(self) -> TrajectoryId:
        return (self.robot, self.session)


@dataclass
class TrajectorySummary:
    bag: str
    odometry_messages: int = 0
    nodes: int = 0
    joined: bool = False
    loops_within: int = 0  # loop factors in the graph with both ends here
    loops_between: int = 0  # ... with one end here
    errors: dict[str, Any] = field(default_factory=dict)


@dataclass
class FleetSummary:
    """What one fleet run did; ``trajectories`` by ``robot/session``."""

    trajectories: dict[str, TrajectorySummary] = field(default_factory=dict)
    loops_sources: list[str] = field(default_factory=list)
    loops_read: int = 0
    loops_added: int = 0
    loop_outliers: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    config: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    out_dir: str = ""


def check_inputs(inputs: list[TrajectoryInput]) -> None:
    """``ConfigError`` for a robot-session given twice or an id that is not a folder name."""
    seen: dict[TrajectoryId, int] = {}
    for number, item in enumerate(inputs, start=1):
        for what, value in (("robot", item.robot), ("session", item.session)):
            problem = name_problem(f"{what} id", value)
            if problem:
                raise ConfigError(f"--trajectory {number}: {problem}")
        if item.id in seen:
            raise ConfigError(
                f"--trajectory {seen[item.id]} and {number} are both robot {item.robot} session "
                f"{item.session}: two robots need two robot ids, two runs of one robot two "
                "session ids"
            )
        seen[item.id] = number


def optimise_fleet(
    odometry: dict[TrajectoryId, Trajectory], loops: list[LoopFactor], config: PoseGraphConfig
) -> PoseGraph:
    """All trajectories' odometry in stamp order (first given first on a tie), each loop once
    the odometry reaches its query stamp, iSAM2 after each message (as the node does)."""
    graph = PoseGraph(config, list(odometry))
    stream = sorted((float(s), i, k) for i, t in enumerate(odometry.values())
                    for k, s in enumerate(t.stamps))  # fmt: skip
    ids, tracks = list(odometry), list(odometry.values())
    order = sorted(loops, key=lambda lp: lp.query_stamp)
    k = 0
    for stamp, i, row in stream:
        graph.add_odometry(stamp, tuple(tracks[i].poses[row]), ids[i])
        while k < len(order) and order[k].query_stamp <= stamp:
            graph.add_loop(order[k])
            k += 1
        graph.update()
    for loop in order[k:]:
        graph.add_loop(loop)
    graph.finish()
    return graph


def run_fleet_posegraph(
    inputs: list[TrajectoryInput],
    loops_paths: list[str | Path],
    out_dir: str | Path = "posegraph_out",
    odom_topic: str = "/odom",
    gt_topic: str | None = None,
    config: PoseGraphConfig | None = None,
    loops_of: list[tuple[TrajectoryId, str | Path]] = (),
) -> FleetSummary:
    """Odometry of every input + the loops of every source -> files in ``out_dir`` (see the
    module docstring); ``loops_of``: sources of one robot-session, whose loop ends that name no
    robot and session are its own. ``PairVPRError`` subclasses for unusable input."""
    config = config or PoseGraphConfig()
    config.validate()
    check_inputs(inputs)
    summary = FleetSummary(config=asdict(config))
    odometry, truth = {}, {}
    for item in inputs:
        scratch = PoseGraphSummary()
        try:
            with open_bag(item.bag) as reader:
                odometry[item.id] = read_track(reader, odom_topic, "odometry", scratch)
                if gt_topic:
                    truth[item.id] = read_track(reader, gt_topic, "ground-truth", scratch)
        except PairVPRError as err:
            raise type(err)(f"trajectory {label(item.id)} ({item.bag}): {err}") from err
        summary.warnings += [f"{label(item.id)}: {w}" for w in scratch.warnings]
        for reason, n in scratch.skipped.items():
            summary.skipped[f"{label(item.id)} {reason}"] = n
        summary.trajectories[label(item.id)] = TrajectorySummary(
            str(item.bag), len(odometry[item.id]) + sum(scratch.skipped.values())
        )
    loops: list[LoopFactor] = []
    for owner, path in [(None, p) for p in loops_paths] + list(loops_of):
        source = read_loops(path)
        summary.loops_sources.append(source.line())
        loops += [own(f, owner) for f in source.factors] if owner else source.factors
    summary.loops_read = len(loops)
    graph = optimise_fleet(odometry, loops, config)
    _summarise(summary, graph)
    with writing_outputs(Path(out_dir), "pose graph's outputs"):
        _write(Path(out_dir), summary, graph, truth)
    return summary


def _summarise(summary: FleetSummary, graph: PoseGraph) -> None:
    summary.loops_added = graph.counts.loops_added
    summary.loop_outliers = int((~graph.loop_inliers()).sum())
    for reason, n in graph.counts.skipped.items():
        summary.skipped[reason] = summary.skipped.get(reason, 0) + n
        if reason.startswith("loop: robot-session "):
            summary.warnings.append(f"{n} loops skipped: {reason[6:]} ({_hint(reason)})")
    for track in graph.tracks:
        item = summary.trajectories[label(track.trajectory)]
        item.nodes, item.joined = len(track.nodes), track.joined
        for entry in graph.loops:
            ends = {graph.tracks.track_of(entry.match_key), graph.tracks.track_of(entry.query_key)}
            if track in ends:
                item.loops_within += len(ends) == 1
                item.loops_between += len(ends) == 2
        if not track.joined:
            summary.warnings.append(
                f"{label(track.trajectory)} never joined the map frame (not "
                f"{graph.config.join_min_loops} agreeing loops to the others): its optimised.tum "
                "is its odometry, in its own frame"
            )


def _hint(reason: str) -> str:
    """What to do about loops whose robot-session the graph cannot place: a named one needs
    its trajectory; loops that name none ('*', a replay without --robot-id) need an owner."""
    if "*" not in reason.split(" ")[2]:  # "loop: robot-session R/S ..."
        return "give its --trajectory ROBOT SESSION BAG"
    return (
        "the loops name no robot or session (a replay without --robot-id): give each such "
        "loops file as --loops-of ROBOT SESSION PATH, the robot-session it was replayed for"
    )


def _write(
    out: Path, summary: FleetSummary, graph: PoseGraph, truth: dict[TrajectoryId, Trajectory]
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    summary.out_dir = str(out)
    before, after = {}, {}
    for track in graph.tracks:
        tid, folder = track.trajectory, out.joinpath(*track.trajectory)
        stamps = graph.node_stamps(tid)
        before[tid] = Trajectory(stamps, graph.odometry_poses(tid))
        after[tid] = Trajectory(stamps, graph.optimised_poses(tid))
        write_tum(folder / "odometry.tum", before[tid])
        write_tum(folder / "optimised.tum", after[tid])
        (folder / "ground_truth.tum").unlink(missing_ok=True)
        if tid in truth:
            write_tum(folder / "ground_truth.tum", truth[tid])
            errors = summary.trajectories[label(tid)].errors
            for name, estimate in (("odometry", before[tid]), ("optimised", after[tid])):
                errors[name] = trajectory_errors(estimate, truth[tid]).to_dict()
    reference = graph.tracks.reference.trajectory
    to_truth = None
    if truth:
        to_truth = reference_alignment(after[reference], truth[reference])
        for tid, estimate in after.items():
            if graph.joined(tid):
                errors = summary.trajectories[label(tid)].errors
                errors["ate_in_reference_frame"] = trajectory_errors(
                    estimate, truth[tid], alignment=to_truth
                ).ate_rmse
    segments = graph.loop_segments()
    between = np.array([graph.tracks.track_of(e.match_key) is not graph.tracks.track_of(
        e.query_key) for e in graph.loops], dtype=bool)  # fmt: skip
    plot_fleet(out / "posegraph.png", before, after, truth, to_truth, segments,
               graph.loop_inliers(), between)  # fmt: skip
    (out / "posegraph.json").write_text(json.dumps(asdict(summary), indent=1) + "\n")


def fleet_main(args: Any, config: PoseGraphConfig) -> None:
    """The ``--trajectory`` form of ``pairvpr-posegraph`` (argparse namespace in, lines out)."""
    if args.inject_false_loops:
        raise ConfigError("--inject-false-loops takes one robot's BAG, not --trajectory")
    if not args.loops and not args.loops_of:
        raise UsageError("--trajectory needs loops: --loops PATH or --loops-of ROBOT SESSION PATH")
    for robot, session, _ in args.loops_of or ():
        for what, value in (("robot id", robot), ("session id", session)):
            problem = name_problem(what, value)
            if problem:
                raise UsageError(f"--loops-of: {problem}")
    inputs = [TrajectoryInput(r, s, Path(b)) for r, s, b in args.trajectory]
    owned = [((r, s), p) for r, s, p in args.loops_of or ()]
    summary = run_fleet_posegraph(inputs, args.loops or [], args.out, args.odom_topic,
                                  args.gt_topic, config, owned)  # fmt: skip
    for warning in summary.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    for line in summary.loops_sources:
        print(f"loops: {line}")
    skipped = sum(summary.skipped.values())
    print(f"{summary.loops_added} loops in the graph ({summary.loop_outliers} outliers), "
          f"{skipped} inputs skipped" + (f": {summary.skipped}" if skipped else ""))  # fmt: skip
    for name, item in summary.trajectories.items():
        line = f"{name}: {item.nodes} nodes, {item.loops_within} loops within, "
        line += f"{item.loops_between} between, {'joined' if item.joined else 'NOT joined'}"
        if "optimised" in item.errors:
            before = item.errors["odometry"]["ate_rmse"]
            after = item.errors["optimised"]["ate_rmse"]
            line += f"; ATE odometry {before:.3f} m -> optimised {after:.3f} m"
        if "ate_in_reference_frame" in item.errors:
            line += f", in the first one's frame {item.errors['ate_in_reference_frame']:.3f} m"
        print(line)
    print(f"outputs in {summary.out_dir}: ROBOT/SESSION/optimised.tum, posegraph.json/.png")
