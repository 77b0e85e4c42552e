"""A Pose3 graph of odometry and loop closures, optimised incrementally with GTSAM's iSAM2.

The same object serves ``pairvpr-posegraph`` (offline, fed from bags) and ``posegraph_node``
(fed from topics): odometry in, loop closures in, corrected trajectories and map->odom out.

* **Trajectories**: one per robot-session (``tracks``), each with its own key character; the
  first is the map frame (its first node is held by a tight prior: the map frame is its odometry
  frame at start). A single robot is the one trajectory ``("", "")``. The others join once their
  loops to joined trajectories agree on where they are (``joining``); until then they wait
  outside the optimisation and their output is their odometry.
* **Nodes** are odometry poses of the robot base, one each time the robot has moved
  ``node_spacing_m`` or turned ``node_spacing_deg`` since the last node.
* **Odometry factors** join consecutive nodes of a trajectory with the odometry's relative pose;
  their sigmas grow with the distance travelled between the nodes (``sigma = floor + per_m *
  metres``), because a ``nav_msgs/Odometry`` pose covariance is that of the accumulated pose
  and says little about one step.
* **Loop factors** join the nodes nearest to a loop's two stamps, in the trajectories its robot
  and session fields name (within one or between two). The loop's camera-frame transform is
  moved to the base frame through ``camera_to_base`` and to the nodes through the short stretch
  of odometry between each stamp and its node. Its 6x6 covariance is converted to GTSAM's order
  and frame and wrapped in a robust kernel (``loop_kernel``): a false loop whose residual stays
  large loses its weight instead of bending the trajectories.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np

from pair_vpr_ros.messages.factor import LoopFactor
from pair_vpr_ros.posegraph import joining, noise
from pair_vpr_ros.posegraph.config import INLIER_CHI2, MAX_PENDING, PoseGraphConfig
from pair_vpr_ros.posegraph.loops import LoopEntry, camera_pose, loop_problem
from pair_vpr_ros.posegraph.tracks import (
    SINGLE,
    Node,
    Track,
    Trajectories,
    TrajectoryId,
    travel,
    waits_for_odometry,
)
from pair_vpr_ros.posegraph.transforms import pose3, pose7, transform_covariance, valid_pose7

SOLO = (SINGLE,)  # the trajectories of a single robot


@dataclass
class GraphCounts:
    """What the graph did with its input: used, gaps, loops added, skipped (by reason)."""

    odometry: int = 0
    nodes: int = 0
    odometry_gaps: int = 0
    loops_added: int = 0
    skipped: Counter[str] = field(default_factory=Counter)


class PoseGraph:
    """Odometry + loop closures of one or more robot-sessions -> optimised base trajectories
    (iSAM2). ``trajectories``: the robot-sessions, the first one the map frame. Not
    thread-safe."""

    def __init__(
        self,
        config: PoseGraphConfig | None = None,
        trajectories: Sequence[TrajectoryId] = (SINGLE,),
    ) -> None:
        self.config = config or PoseGraphConfig()
        self.config.validate()
        self.tracks = Trajectories(self.config.history_period_s, self.config.max_odom_gap_s)
        for trajectory in trajectories:
            self.tracks.add(tuple(trajectory))
        self.loops: list[LoopEntry] = []  # loop factors in the graph
        self.waiting: list[LoopEntry] = []  # loops that touch a trajectory not yet joined
        self.pending: list[LoopFactor] = []  # loops whose stamps the odometry has not reached
        self.counts = GraphCounts()
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        params.relinearizeSkip = 1
        self._isam = gtsam.ISAM2(params)
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._new_loops = 0  # loop factors in the batch since the last update
        self._settle = 0  # iSAM2 iterations still to run after the last loop
        self._estimate = gtsam.Values()
        self._camera = pose3(self.config.camera_to_base)

    @property
    def nodes(self) -> list[Node]:
        """The first trajectory's nodes (the single robot's)."""
        return self.tracks.reference.nodes

    # ---- input ---------------------------------------------------------------------------------
    def add_odometry(
        self, stamp: float, pose: tuple[float, ...], trajectory: TrajectoryId | None = None
    ) -> str | None:
        """Feed one odometry pose of a trajectory's base (None: the first trajectory); returns
        why it was skipped (None: used)."""
        track = self.tracks.get(trajectory)
        reason = valid_pose7(pose) or (None if math.isfinite(stamp) else "stamp is not finite")
        latest = track.history.latest_stamp
        if reason is None and latest is not None and stamp <= latest:
            reason = "odometry stamp not after the previous one"
        if reason is not None:
            self.counts.skipped[f"odometry: {reason}"] += 1
            return reason
        if latest is not None and stamp - latest > self.config.max_odom_gap_s:
            self.counts.odometry_gaps += 1
        self.counts.odometry += 1
        track.history.add(stamp, tuple(float(v) for v in pose))
        odom = pose3(pose)
        if not track.nodes or self._far_enough(track.nodes[-1].odom, odom):
            self._add_node(track, stamp, odom)
        self._retry_pending()
        return None

    def add_loop(self, loop: LoopFactor) -> str:
        """Feed one loop closure: "added", "pending" (waits for odometry), "waiting" (a
        trajectory it touches has not joined yet), or the skip reason."""
        reason = loop_problem(loop)
        ends = self.tracks.ends(loop) if reason is None else None
        if isinstance(ends, str):
            reason = ends
        elif ends is not None and waits_for_odometry(loop, *ends):
            self.pending.append(loop)
            if len(self.pending) > MAX_PENDING:  # the odometry stopped: keep the newest
                self.pending.pop(0)
                self.counts.skipped["loop: waited too long for odometry"] += 1
            return "pending"
        if reason is None:
            result = self._insert_loop(loop, *ends)
            if result in ("added", "waiting"):
                return result
            reason = result
        self.counts.skipped[f"loop: {_reason_kind(reason)}"] += 1
        return reason

    def finish(self) -> None:
        """Give up on loops still waiting for odometry (end of a bag) and optimise."""
        if self.pending:
            self.counts.skipped["loop: stamp after the newest odometry"] += len(self.pending)
        self.pending.clear()
        if self.waiting:
            self.counts.skipped["loop: a trajectory it touches never joined"] += len(self.waiting)
        while self.update():
            pass

    # ---- optimisation --------------------------------------------------------------------------
    def update(self) -> bool:
        """Run iSAM2 on the factors added since the last call, or one more iteration after a
        loop (``loop_iterations``); False when there was nothing to do."""
        if self._new_factors.size() == 0:
            if self._settle <= 0:
                return False
            self._settle -= 1
            self._isam.update()
            self._estimate = self._isam.calculateEstimate()
            return True
        self._isam.update(self._new_factors, self._new_values)
        if self._new_loops:
            self._settle = self.config.loop_iterations
        self._new_factors = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._new_loops = 0
        self._estimate = self._isam.calculateEstimate()
        return True

    # ---- output --------------------------------------------------------------------------------
    def node_stamps(self, trajectory: TrajectoryId | None = None) -> np.ndarray:
        """``[K]`` float64 stamps of a trajectory's nodes (None: the first trajectory)."""
        return self.tracks.get(trajectory).node_stamps()

    def odometry_poses(self, trajectory: TrajectoryId | None = None) -> np.ndarray:
        """``[K, 7]`` odometry poses of a trajectory's nodes."""
        nodes = self.tracks.get(trajectory).nodes
        return np.array([pose7(n.odom) for n in nodes], dtype=np.float64).reshape(-1, 7)

    def optimised_poses(self, trajectory: TrajectoryId | None = None) -> np.ndarray:
        """``[K, 7]`` optimised poses of a trajectory's nodes in the map frame (odometry for
        nodes not yet optimised; a trajectory that has not joined: its odometry frame)."""
        out = [pose7(self._current(n.key)) for n in self.tracks.get(trajectory).nodes]
        return np.array(out, dtype=np.float64).reshape(-1, 7)

    def joined(self, trajectory: TrajectoryId | None = None) -> bool:
        """Whether a trajectory is in the map frame (the first one always is)."""
        return self.tracks.get(trajectory).joined

    def map_to_odom(self, trajectory: TrajectoryId | None = None) -> gtsam.Pose3:
        """The correction ``T_map_odom`` = optimised newest node * its odometry pose ^-1
        (identity before the first node or the trajectory's join)."""
        track = self.tracks.get(trajectory)
        if not track.nodes or not self._estimate.exists(track.nodes[-1].key):
            return gtsam.Pose3()
        last = track.nodes[-1]
        return self._estimate.atPose3(last.key).compose(last.odom.inverse())

    def loop_residuals(self) -> np.ndarray:
        """``[L]`` squared Mahalanobis residual of each added loop at the current estimate, under
        its own covariance (an inlier is chi-square with 6 degrees of freedom: below
        ``INLIER_CHI2`` 99 % of the time)."""
        out = []
        for lf in self.loops:
            hx = self._current(lf.match_key).between(self._current(lf.query_key))
            r = gtsam.Pose3.Logmap(lf.measured.between(hx))
            out.append(float(r @ lf.information @ r))
        return np.array(out, dtype=np.float64)

    def loop_inliers(self) -> np.ndarray:
        """``[L]`` bool: the loop agrees with the optimised trajectory (residual < INLIER_CHI2)."""
        return self.loop_residuals() < INLIER_CHI2

    def loop_segments(self) -> np.ndarray:
        """``[L, 2, 3]`` optimised positions of each added loop's match and query nodes."""
        ends = [(self._current(lf.match_key).translation(),
                 self._current(lf.query_key).translation()) for lf in self.loops]  # fmt: skip
        return np.array(ends, dtype=np.float64).reshape(-1, 2, 3)

    def _current(self, key: int) -> gtsam.Pose3:
        """A node's latest value: iSAM2's estimate, else its initial value, else its odometry."""
        for values in (self._estimate, self._new_values):
            if values.exists(key):
                return values.atPose3(key)
        return self.tracks.node(key).odom

    # ---- internals -----------------------------------------------------------------------------
    def _far_enough(self, a: gtsam.Pose3, b: gtsam.Pose3) -> bool:
        delta = a.between(b)
        turned = math.degrees(np.linalg.norm(gtsam.Rot3.Logmap(delta.rotation())))
        moved = float(np.linalg.norm(delta.translation()))
        return moved >= self.config.node_spacing_m or turned >= self.config.node_spacing_deg

    def _add_node(self, track: Track, stamp: float, odom: gtsam.Pose3) -> None:
        before = track.nodes[-1] if track.nodes else None
        index = len(track.nodes)
        node = Node(track.key(index), index, stamp, odom, travel(before, odom))
        if before is None:
            if track is self.tracks.reference:
                tight = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))
                self._new_factors.add(gtsam.PriorFactorPose3(node.key, odom, tight))
                self._new_values.insert(node.key, odom)
        else:
            delta = before.odom.between(odom)
            sigmas = noise.odometry_noise(delta, self.config)
            factor = gtsam.BetweenFactorPose3(before.key, node.key, delta, sigmas)
            if track.joined:
                self._new_factors.add(factor)
                self._new_values.insert(node.key, self._current(before.key).compose(delta))
            else:
                track.waiting.append(factor)
        track.nodes.append(node)
        self.counts.nodes += 1

    def _insert_loop(self, loop: LoopFactor, query_track: Track, match_track: Track) -> str:
        if not query_track.nodes or not match_track.nodes:
            return "no odometry yet"
        tolerance = self.config.stamp_tolerance_s
        match = match_track.anchor(loop.match_stamp, tolerance)
        query = query_track.anchor(loop.query_stamp, tolerance)
        for end in (match, query):
            if isinstance(end, str):
                return end
        (match_node, match_off), (query_node, query_off) = match, query
        if match_node.key == query_node.key:
            return "both loop stamps fall on the same graph node"
        base_loop = self._camera.compose(camera_pose(loop)).compose(self._camera.inverse())
        measured = match_off.compose(base_loop).compose(query_off.inverse())
        # Covariance of the query camera's right perturbation -> of the base's, then of the node's.
        cov = transform_covariance(loop.gtsam_covariance(), self._camera)
        cov = transform_covariance(cov, query_off)
        entry = LoopEntry(match_node.key, query_node.key, loop, measured, np.linalg.inv(cov))
        width = self.config.loop_kernel_width
        joined = match_track.joined and query_track.joined
        if joined and self.config.innovation_kernel:
            self.update()  # the nodes must be in iSAM2 for their marginals
            width *= noise.drift_scale(self._isam, match_node.key, query_node.key, measured, cov)
        entry.noise = noise.robust(gtsam.noiseModel.Gaussian.Covariance(cov), self.config, width)
        if not joined:
            self.waiting.append(entry)
            self._try_joins()
            return "added" if any(e is entry for e in self.loops) else "waiting"
        self._add_loop_factor(entry)
        return "added"

    def _add_loop_factor(self, entry: LoopEntry) -> None:
        self._new_loops += 1
        self._new_factors.add(entry.between())
        self.loops.append(entry)
        self.counts.loops_added += 1

    def _try_joins(self) -> None:
        """Join every trajectory whose waiting loops agree on its frame (``joining``), then
        move the loops whose trajectories have all joined into the graph."""
        joined_one = True
        while joined_one:
            joined_one = False
            for track in self.tracks:
                if not track.joined and self._try_join(track):
                    joined_one = True
        waiting, self.waiting = self.waiting, []
        for entry in waiting:
            if self._joined(entry.match_key) and self._joined(entry.query_key):
                self._add_loop_factor(entry)
            else:
                self.waiting.append(entry)

    def _joined(self, key: int) -> bool:
        return self.tracks.track_of(key).joined

    def _try_join(self, track: Track) -> bool:
        found = joining.candidates(track, self.waiting, self.tracks, self._current)
        chosen = joining.first_consistent(found, self.config)
        if chosen is None:
            return False
        for node in track.nodes:  # the whole trajectory, moved by the chosen alignment
            self._new_values.insert(node.key, chosen.alignment.compose(node.odom))
        for factor in track.waiting:
            self._new_factors.add(factor)
        track.waiting.clear()
        track.joined = True
        return True

    def _retry_pending(self) -> None:
        waiting = []
        for loop in self.pending:
            ends = self.tracks.ends(loop)
            if not isinstance(ends, str) and waits_for_odometry(loop, *ends):
                waiting.append(loop)
                continue
            reason = ends if isinstance(ends, str) else self._insert_loop(loop, *ends)
            if reason not in ("added", "waiting"):
                self.counts.skipped[f"loop: {_reason_kind(reason)}"] += 1
        self.pending = waiting


def _reason_kind(reason: str) -> str:
    """A reason without its details in parentheses, for counting."""
    return reason.split(" (")[0]
