"""How a robot-session joins the graph: its frame from its loops to trajectories already there.

Until it joins, a trajectory is not in the optimisation (its nodes have no values in iSAM2, its
odometry factors and loops wait): nothing ties its odometry frame to the map frame, and a guess
would bend the others. Each loop between it and a joined trajectory gives a *candidate*
alignment ``T_map_odom`` (the joined node's estimate, the loop's measured pose, the detached
node's odometry). It joins with the first candidate that ``join_min_loops - 1`` others agree
with: two candidates agree when the poses they give the same node differ by at most
``join_tolerance_m`` / ``join_tolerance_deg``, widened by ``join_tolerance_per_m`` of the
odometry travelled between their loops (drift). A lone false loop between robots then cannot
drag a whole trajectory across the map; later false loops meet the robust kernel as usual.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np

from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.loops import LoopEntry
from pair_vpr_ros.posegraph.tracks import Node, Track, Trajectories


@dataclass
class Candidate:
    """A loop between a detached node and a joined one, and the alignment it implies."""

    detached: Node
    joined: Node
    alignment: gtsam.Pose3  # T_map_odom of the detached trajectory


def candidate(
    measured: gtsam.Pose3,
    match: Node,
    query: Node,
    match_pose: gtsam.Pose3 | None,
    query_pose: gtsam.Pose3 | None,
) -> Candidate:
    """The alignment a loop ``measured = T_match_query`` (between the nodes' base frames) gives
    the detached end; exactly one of ``match_pose`` / ``query_pose`` (the joined end's current
    estimate in the map frame) is given."""
    if match_pose is not None:
        placed, detached, joined = match_pose.compose(measured), query, match
    else:
        placed, detached, joined = query_pose.compose(measured.inverse()), match, query
    return Candidate(detached, joined, placed.compose(detached.odom.inverse()))


def agree(a: Candidate, b: Candidate, config: PoseGraphConfig) -> bool:
    """Whether ``a``'s alignment puts ``b``'s detached node where ``b`` does, within tolerance."""
    pa = a.alignment.compose(b.detached.odom)
    pb = b.alignment.compose(b.detached.odom)
    delta = pa.between(pb)
    travelled = abs(a.detached.travel - b.detached.travel)
    if gtsam.Symbol(a.joined.key).chr() == gtsam.Symbol(b.joined.key).chr():
        travelled += abs(a.joined.travel - b.joined.travel)
    metres = config.join_tolerance_m + config.join_tolerance_per_m * travelled
    degrees = config.join_tolerance_deg * metres / config.join_tolerance_m
    turned = math.degrees(float(np.linalg.norm(gtsam.Rot3.Logmap(delta.rotation()))))
    return float(np.linalg.norm(delta.translation())) <= metres and turned <= degrees


def first_consistent(candidates: list[Candidate], config: PoseGraphConfig) -> Candidate | None:
    """The earliest candidate that ``join_min_loops`` candidates (itself included) agree with."""
    for a in candidates:
        if sum(agree(a, b, config) for b in candidates) >= config.join_min_loops:
            return a
    return None


def candidates(
    track: Track,
    waiting: list[LoopEntry],
    tracks: Trajectories,
    current: Callable[[int], gtsam.Pose3],
) -> list[Candidate]:
    """The candidates of the ``waiting`` loops between ``track`` (not joined) and a joined
    trajectory, in the order the loops came; ``current(key)``: a joined node's estimate."""
    out = []
    for entry in waiting:
        match, query = tracks.node(entry.match_key), tracks.node(entry.query_key)
        match_track, query_track = tracks.track_of(match.key), tracks.track_of(query.key)
        if query_track is track and match_track.joined:
            out.append(candidate(entry.measured, match, query, current(match.key), None))
        elif match_track is track and query_track.joined:
            out.append(candidate(entry.measured, match, query, None, current(query.key)))
    return out
