"""One trajectory per robot-session: its key space, odometry history and nodes.

A trajectory is named by ``(robot, session)``; ``("", "")`` is the single robot of the old
format. Each gets one ``gtsam.Symbol`` character, in the order trajectories are added (the first
gets ``x``, so a single robot's keys are ``x0, x1, ...`` as before): the same list of
trajectories always gives the same keys. ``""`` in a trajectory's robot or session is a
wildcard when loops are resolved: ``("a", "")`` takes the loops of robot ``a`` in any session (a
node that does not know the session id its vpr_node picked at start).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import gtsam
import numpy as np

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.messages.factor import LoopFactor
from pair_vpr_ros.posegraph.odometry import OdometryHistory

TrajectoryId = tuple[str, str]  # (robot, session)
SINGLE: TrajectoryId = ("", "")
KEY_CHARS = "xabcdefghijklmnopqrstuvwyzABCDEFGHIJKLMNOPQRSTUVWXYZ"  # 'x' first: old keys stay


def label(trajectory: TrajectoryId) -> str:
    """``robot/session`` for messages (``*`` for an empty part)."""
    robot, session = trajectory
    return f"{robot or '*'}/{session or '*'}"


@dataclass
class Node:
    """One graph node: its gtsam key, index in its trajectory, odometry stamp (s), odometry
    pose of the base and the odometry distance travelled since the trajectory's first node."""

    key: int
    index: int
    stamp: float
    odom: gtsam.Pose3
    travel: float = 0.0


@dataclass(eq=False)
class Track:
    """One robot-session. ``joined``: its nodes are in the optimisation (the first trajectory
    from the start, the others once their loops place them in its frame); until then its
    odometry factors wait in ``waiting``."""

    trajectory: TrajectoryId
    char: str
    history: OdometryHistory
    nodes: list[Node] = field(default_factory=list)
    joined: bool = False
    waiting: list[gtsam.NonlinearFactor] = field(default_factory=list)

    def key(self, index: int) -> int:
        return gtsam.symbol(self.char, index)

    def node_stamps(self) -> np.ndarray:
        """``[K]`` float64 stamps of the nodes."""
        return np.array([n.stamp for n in self.nodes], dtype=np.float64)

    def nearest_node(self, stamp: float) -> Node:
        stamps = self.node_stamps()
        i = int(np.searchsorted(stamps, stamp))
        candidates = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
        return self.nodes[min(candidates, key=lambda j: abs(stamps[j] - stamp))]

    def anchor(self, stamp: float, tolerance: float) -> tuple[Node, gtsam.Pose3] | str:
        """The node nearest to ``stamp`` and the base's pose at ``stamp`` in that node's frame,
        or why there is none."""
        odom = self.history.pose_at(stamp, tolerance)
        if isinstance(odom, str):
            return odom
        node = self.nearest_node(stamp)
        return node, node.odom.between(odom)


class Trajectories:
    """The graph's robot-sessions in the order added; the first is the reference (map) frame."""

    def __init__(self, period_s: float, max_gap_s: float) -> None:
        self._period_s, self._max_gap_s = period_s, max_gap_s
        self.tracks: dict[TrajectoryId, Track] = {}
        self._by_char: dict[str, Track] = {}

    def add(self, trajectory: TrajectoryId) -> Track:
        """A new trajectory; ``ConfigError`` for one added twice or one too many."""
        robot, session = trajectory
        if not (isinstance(robot, str) and isinstance(session, str)):
            raise ConfigError(f"trajectory {trajectory!r}: robot and session must be strings")
        if trajectory in self.tracks:
            raise ConfigError(
                f"trajectory {label(trajectory)} is given twice: each robot-session needs its "
                "own (robot, session) id"
            )
        if len(self.tracks) == len(KEY_CHARS):
            raise ConfigError(f"a pose graph holds at most {len(KEY_CHARS)} robot-sessions")
        track = Track(trajectory, KEY_CHARS[len(self.tracks)],
                      OdometryHistory(self._period_s, self._max_gap_s))  # fmt: skip
        track.joined = not self.tracks  # the first one is the map frame
        self.tracks[trajectory] = track
        self._by_char[track.char] = track
        return track

    @property
    def reference(self) -> Track:
        return next(iter(self.tracks.values()))

    def __iter__(self):
        return iter(self.tracks.values())

    def __len__(self) -> int:
        return len(self.tracks)

    def get(self, trajectory: TrajectoryId | None) -> Track:
        """The track of ``trajectory`` (None: the first); ``ConfigError`` when unknown."""
        if trajectory is None:
            return self.reference
        track = self.tracks.get(tuple(trajectory))
        if track is None:
            raise ConfigError(f"trajectory {label(tuple(trajectory))} is not in the pose graph")
        return track

    def node(self, key: int) -> Node:
        symbol = gtsam.Symbol(key)
        return self._by_char[chr(symbol.chr())].nodes[symbol.index()]

    def track_of(self, key: int) -> Track:
        return self._by_char[chr(gtsam.Symbol(key).chr())]

    def resolve(self, robot: str, session: str) -> Track | str:
        """The track a loop's side names: an exact (robot, session), else the one track whose
        empty parts match; or why there is none."""
        exact = self.tracks.get((robot, session))
        if exact is not None:
            return exact
        near = [t for t in self if t.trajectory[0] in ("", robot)
                and t.trajectory[1] in ("", session)]  # fmt: skip
        if len(near) == 1:
            return near[0]
        what = "matches several trajectories" if near else "is not in the graph"
        return f"robot-session {label((robot, session))} {what} (trajectories: {self.labels()})"

    def ends(self, loop: LoopFactor) -> tuple[Track, Track] | str:
        """The (query, match) tracks a loop names, or why it names none."""
        query = self.resolve(loop.query_robot, loop.query_session)
        match = self.resolve(loop.match_robot, loop.match_session)
        for end in (query, match):
            if isinstance(end, str):
                return end
        sides = ((loop.query_robot, loop.query_session), (loop.match_robot, loop.match_session))
        if query is match and sides[0] != sides[1]:
            return (f"loop between robot-sessions {label(sides[0])} and {label(sides[1])} falls "
                    f"on one trajectory ({self.labels()}): give each its own")  # fmt: skip
        return query, match

    def labels(self) -> str:
        return ", ".join(label(t) for t in self.tracks)


def waits_for_odometry(loop: LoopFactor, query: Track, match: Track) -> bool:
    """Whether a loop's stamp lies after its trajectory's newest odometry (so far)."""
    for track, stamp in ((query, loop.query_stamp), (match, loop.match_stamp)):
        latest = track.history.latest_stamp
        if latest is not None and stamp > latest:
            return True
    return False


def travel(previous: Node | None, odom: gtsam.Pose3) -> float:
    """Odometry distance (m) from the trajectory's first node to ``odom`` via ``previous``."""
    if previous is None:
        return 0.0
    step = float(np.linalg.norm(previous.odom.between(odom).translation()))
    return previous.travel + (step if math.isfinite(step) else 0.0)
