"""Prior sessions in the pose graph: the keyframe poses of saved place maps as trajectories.

A saved map (vpr_node's ``save_map``, a replay's ``map/``) holds, per keyframe, its robot,
session, stamp and pose in that session's odometry frame (attached from the odometry when the
keyframe was made). ``read_prior_sessions`` turns every robot-session of the given maps into a
trajectory whose odometry is its keyframes' poses, in stamp order; ``graph_with_priors`` puts
them in a ``PoseGraph`` **first** (the first prior session, in the order the maps are given and
then by first keyframe id, is the map frame) and the live trajectories after them, and feeds the
prior odometry before any live message. A live robot's loop into a prior keyframe (its
``match_robot`` / ``match_session`` / ``match_stamp``) then lands on that trajectory, and the
live robot joins the prior map's frame like any other trajectory (``joining``).

Keyframes without a pose, without a robot or session, with a pose the graph cannot use or with
the stamp of an earlier keyframe of their session are counted skips (``PriorSessions.skipped``,
then the graph's ``counts.skipped``); a session left with no keyframe is not a trajectory (a
note says so). ROS-free: ``posegraph_node``'s ``prior_map_dirs`` calls these two functions.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pair_vpr_ros.errors import ConfigError, MapError
from pair_vpr_ros.identity import DEFAULT_ROBOT, LEGACY_SESSION, name_problem
from pair_vpr_ros.loops.prior_maps import prior_folder
from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.graph import PoseGraph
from pair_vpr_ros.posegraph.tracks import TrajectoryId, label
from pair_vpr_ros.posegraph.transforms import valid_pose7

WHAT = "prior_map_dirs"


@dataclass
class PriorSession:
    """One prior robot-session: ``stamps [K]`` (s, increasing) and ``poses [K, 7]`` of its
    keyframes, and the map folders they came from."""

    trajectory: TrajectoryId
    stamps: np.ndarray
    poses: np.ndarray
    maps: list[str] = field(default_factory=list)


@dataclass
class PriorSessions:
    """The prior sessions of some maps, in map-frame order, and what was skipped."""

    sessions: list[PriorSession] = field(default_factory=list)
    skipped: Counter[str] = field(default_factory=Counter)
    notes: list[str] = field(default_factory=list)

    @property
    def trajectories(self) -> list[TrajectoryId]:
        return [s.trajectory for s in self.sessions]


def read_prior_sessions(dirs: Sequence[str | Path], what: str = WHAT) -> PriorSessions:
    """The robot-sessions of the saved maps in ``dirs`` (opened read-only; any model) ->
    ``PriorSessions``. ``ConfigError``: a folder missing or given twice; ``MapError``: not a
    map, or damaged (each names the folder). A session in two maps is one trajectory."""
    rows: dict[TrajectoryId, list[tuple[float, tuple[float, ...]]]] = {}
    sources: dict[TrajectoryId, list[str]] = {}
    out, seen = PriorSessions(), set()
    for given in dirs:
        path = prior_folder(given, seen, f"{what}:", "vpr_node's save_map, a replay's map/")
        metas = _keyframes(path, given, what)
        for meta in metas:
            reason = _problem(meta.robot, meta.session, meta.pose)
            if reason is not None:
                out.skipped[f"prior keyframe: {reason}"] += 1
                continue
            trajectory = (meta.robot, meta.session)
            rows.setdefault(trajectory, []).append((float(meta.stamp), tuple(meta.pose)))
            if str(path) not in sources.setdefault(trajectory, []):
                sources[trajectory].append(str(path))
        out.notes.append(f"{what}: {path}: {len(metas)} keyframes")
    for trajectory, items in rows.items():
        out.sessions.append(_session(trajectory, items, sources[trajectory], out.skipped))
    return out


def _keyframes(path: Path, given: str | Path, what: str) -> list:
    """Every keyframe's metadata of the map in ``path`` (read-only: nothing is written)."""
    legacy = (DEFAULT_ROBOT, LEGACY_SESSION)  # a format-1 map's names, as `pairvpr-map info`
    try:
        with PlaceMap.load(path, read_only=True, legacy_identity=legacy) as place_map:
            return place_map.all_meta()
    except MapError as err:
        raise type(err)(f"{what}: {given} cannot be used: {err}") from err


def _problem(robot: str, session: str, pose) -> str | None:
    if not robot or not session:
        return "no robot or session (a loop cannot name it)"
    if name_problem("robot", robot) or name_problem("session", session):
        return "robot or session id breaks the identity rule (identity.py)"
    if pose is None:
        return "no pose"
    return valid_pose7(pose)


def _session(
    trajectory: TrajectoryId, items: list, maps: list[str], skipped: Counter[str]
) -> PriorSession:
    items = sorted(items, key=lambda item: item[0])  # stable: the first map's keyframe first
    stamps, poses = [], []
    for stamp, pose in items:
        if stamps and stamp <= stamps[-1]:
            skipped["prior keyframe: stamp of another keyframe of its session"] += 1
            continue
        stamps.append(stamp)
        poses.append(pose)
    return PriorSession(trajectory, np.array(stamps, dtype=np.float64),
                        np.array(poses, dtype=np.float64).reshape(-1, 7), maps)  # fmt: skip


def graph_with_priors(
    config: PoseGraphConfig, priors: PriorSessions, live: Sequence[TrajectoryId]
) -> PoseGraph:
    """A ``PoseGraph`` of the prior sessions (the first one the map frame), then the ``live``
    trajectories, with every prior keyframe pose fed as that session's odometry and optimised.
    ``ConfigError`` when a live trajectory is a prior session (a session id names one
    recording)."""
    for trajectory in live:
        for session in priors.sessions:
            if tuple(trajectory) == session.trajectory:
                raise ConfigError(
                    f"trajectories: robot-session {label(session.trajectory)} is a prior session "
                    f"(in {', '.join(session.maps)}): a session id names one recording, so give "
                    "the live robot a new session id (or leave SESSION empty)"
                )
    try:
        graph = PoseGraph(config, [*priors.trajectories, *live])
    except ConfigError as err:
        raise ConfigError(f"{err} (prior sessions: {len(priors.sessions)})") from err
    for session in priors.sessions:
        for stamp, pose in zip(session.stamps, session.poses, strict=True):
            graph.add_odometry(float(stamp), tuple(pose), session.trajectory)
    graph.counts.skipped.update(priors.skipped)
    while graph.update():
        pass
    return graph
