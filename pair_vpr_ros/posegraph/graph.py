"""A Pose3 graph of odometry and loop closures, optimised incrementally with GTSAM's iSAM2.

The same object serves ``pairvpr-posegraph`` (offline, fed from a bag) and ``posegraph_node``
(fed from topics): odometry in, loop closures in, corrected trajectory and map->odom out.

* **Nodes** are odometry poses of the robot base, one each time the robot has moved
  ``node_spacing_m`` or turned ``node_spacing_deg`` since the last node. The first is held by a
  tight prior: the map frame is the odometry frame at start.
* **Odometry factors** join consecutive nodes with the odometry's relative pose; their sigmas grow
  with the distance travelled between the nodes (``sigma = floor + per_m * metres``), because a
  ``nav_msgs/Odometry`` pose covariance is that of the accumulated pose and says little about
  one step.
* **Loop factors** join the nodes nearest to a loop's two stamps. The loop's camera-frame
  transform is moved to the base frame through ``camera_to_base`` (the camera's pose in the base
  frame) and to the nodes through the short stretch of odometry between each stamp and its node.
  Its 6x6 covariance is converted to GTSAM's order and frame and wrapped in a robust kernel
  (``loop_kernel``): a false loop whose residual stays large loses its weight instead of bending
  the trajectory.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import gtsam
import numpy as np

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.loop_factor import LoopFactor
from pair_vpr_ros.posegraph.loops import LoopEntry, camera_pose, loop_problem
from pair_vpr_ros.posegraph.odometry import OdometryHistory
from pair_vpr_ros.posegraph.transforms import pose3, pose7, transform_covariance, valid_pose7

IDENTITY = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
KERNELS = ("cauchy", "huber", "none")
INLIER_CHI2 = 16.81  # chi-square, 6 degrees of freedom, 99 %
MAX_PENDING = 1000  # loops waiting for odometry; beyond this the oldest is dropped (counted)


@dataclass(frozen=True)
class PoseGraphConfig:
    """Settings of ``PoseGraph`` (defaults chosen on demo world seed 8)."""

    node_spacing_m: float = 1.0  # a new node after this much travel ...
    node_spacing_deg: float = 10.0  # ... or this much turning
    odom_sigma_m: float = 0.01  # translation sigma of an odometry factor: floor ...
    odom_sigma_per_m: float = 0.1  # ... plus this per metre between the nodes
    odom_sigma_deg: float = 0.05  # rotation sigma: floor ...
    odom_sigma_deg_per_m: float = 0.5  # ... plus this per metre
    loop_kernel: str = "cauchy"  # robust kernel on loop factors: cauchy, huber or none
    loop_kernel_width: float = 2.0  # kernel width in sigmas of the loop's own covariance
    # Widen each loop's kernel by the graph's own uncertainty about the two nodes (a lone loop
    # after a large drift is then followed, not down-weighted) - but early false loops get in
    # too: off by default (seed 8 with 10 % false loops: ATE 0.21 m off, 15 m on).
    innovation_kernel: bool = False
    camera_to_base: tuple[float, ...] = IDENTITY  # pose of the camera in the base frame
    stamp_tolerance_s: float = 0.5  # a loop stamp may lie this far outside the odometry
    max_odom_gap_s: float = 1.0  # odometry messages further apart than this form a gap
    history_period_s: float = 0.05  # odometry kept for placing loop stamps, at most every ...
    relinearize_threshold: float = 0.1  # iSAM2: relinearise variables that moved this much
    # After a loop, this many more iSAM2 iterations, one per later update() call (the node calls
    # it for every odometry message), so the robust kernel converges even when the robot stops.
    loop_iterations: int = 10

    def validate(self) -> None:
        """Raise ``ConfigError`` naming the first bad setting."""
        positive = ("node_spacing_m", "node_spacing_deg", "odom_sigma_m", "odom_sigma_deg")
        positive += ("loop_kernel_width", "max_odom_gap_s", "relinearize_threshold")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"pose graph: {name}={value!r} must be a positive number")
        for name in ("odom_sigma_per_m", "odom_sigma_deg_per_m", "stamp_tolerance_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"pose graph: {name}={value!r} must be a number >= 0")
        if not (math.isfinite(self.history_period_s) and self.history_period_s >= 0):
            raise ConfigError(
                f"pose graph: history_period_s={self.history_period_s!r} must be >= 0"
            )
        if self.loop_kernel not in KERNELS:
            raise ConfigError(
                f"pose graph: loop_kernel={self.loop_kernel!r} must be one of {', '.join(KERNELS)}"
            )
        if not 0 <= self.loop_iterations <= 100:
            raise ConfigError(f"pose graph: loop_iterations={self.loop_iterations} must be 0-100")
        reason = valid_pose7(self.camera_to_base)
        if reason is not None:
            raise ConfigError(f"pose graph: camera_to_base: {reason}")


@dataclass
class Node:
    """One graph node: odometry stamp (s) and odometry pose of the base."""

    key: int
    stamp: float
    odom: gtsam.Pose3


@dataclass
class GraphCounts:
    """What the graph did with its input: used, gaps, loops added, skipped (by reason)."""

    odometry: int = 0
    nodes: int = 0
    odometry_gaps: int = 0
    loops_added: int = 0
    skipped: Counter[str] = field(default_factory=Counter)


class PoseGraph:
    """Odometry + loop closures -> optimised base trajectory (iSAM2). Not thread-safe."""

    def __init__(self, config: PoseGraphConfig | None = None) -> None:
        self.config = config or PoseGraphConfig()
        self.config.validate()
        self.history = OdometryHistory(self.config.history_period_s, self.config.max_odom_gap_s)
        self.nodes: list[Node] = []
        self.loops: list[LoopEntry] = []
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

    # ---- input ---------------------------------------------------------------------------------
    def add_odometry(self, stamp: float, pose: tuple[float, ...]) -> str | None:
        """Feed one odometry pose of the base; returns why it was skipped (None: used)."""
        reason = valid_pose7(pose) or (None if math.isfinite(stamp) else "stamp is not finite")
        latest = self.history.latest_stamp
        if reason is None and latest is not None and stamp <= latest:
            reason = "odometry stamp not after the previous one"
        if reason is not None:
            self.counts.skipped[f"odometry: {reason}"] += 1
            return reason
        if latest is not None and stamp - latest > self.config.max_odom_gap_s:
            self.counts.odometry_gaps += 1
        self.counts.odometry += 1
        self.history.add(stamp, tuple(float(v) for v in pose))
        odom = pose3(pose)
        if not self.nodes:
            self._add_node(stamp, odom, prior=True)
        elif self._far_enough(self.nodes[-1].odom, odom):
            self._add_node(stamp, odom)
        self._retry_pending()
        return None

    def add_loop(self, loop: LoopFactor) -> str:
        """Feed one loop closure: "added", "pending" (waits for odometry), or the skip reason."""
        reason = loop_problem(loop)
        if reason is None and self.history.latest_stamp is not None:
            if max(loop.query_stamp, loop.match_stamp) > self.history.latest_stamp:
                self.pending.append(loop)
                if len(self.pending) > MAX_PENDING:  # the odometry stopped: keep the newest
                    self.pending.pop(0)
                    self.counts.skipped["loop: waited too long for odometry"] += 1
                return "pending"
        if reason is None:
            reason = self._insert_loop(loop)
        if reason is not None:
            self.counts.skipped[f"loop: {_reason_kind(reason)}"] += 1
            return reason
        return "added"

    def finish(self) -> None:
        """Give up on loops still waiting for odometry (end of a bag) and optimise."""
        if self.pending:
            self.counts.skipped["loop: stamp after the newest odometry"] += len(self.pending)
        self.pending.clear()
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
    def node_stamps(self) -> np.ndarray:
        """``[K]`` float64 stamps of the nodes."""
        return np.array([n.stamp for n in self.nodes], dtype=np.float64)

    def odometry_poses(self) -> np.ndarray:
        """``[K, 7]`` odometry poses of the nodes."""
        return np.array([pose7(n.odom) for n in self.nodes], dtype=np.float64).reshape(-1, 7)

    def optimised_poses(self) -> np.ndarray:
        """``[K, 7]`` optimised poses of the nodes (odometry for nodes not yet optimised)."""
        out = [pose7(self._estimate_or_odometry(n.key)) for n in self.nodes]
        return np.array(out, dtype=np.float64).reshape(-1, 7)

    def map_to_odom(self) -> gtsam.Pose3:
        """The correction ``T_map_odom`` = optimised newest node * its odometry pose ^-1."""
        if not self.nodes:
            return gtsam.Pose3()
        last = self.nodes[-1]
        key = gtsam.symbol("x", last.key)
        if not self._estimate.exists(key):
            return gtsam.Pose3()
        return self._estimate.atPose3(key).compose(last.odom.inverse())

    def loop_residuals(self) -> np.ndarray:
        """``[L]`` squared Mahalanobis residual of each added loop at the current estimate, under
        its own covariance (an inlier is chi-square with 6 degrees of freedom: below
        ``INLIER_CHI2`` 99 % of the time)."""
        out = []
        for lf in self.loops:
            hx = self._relative(lf.match_key, lf.query_key)
            r = gtsam.Pose3.Logmap(lf.measured.between(hx))
            out.append(float(r @ lf.information @ r))
        return np.array(out, dtype=np.float64)

    def loop_inliers(self) -> np.ndarray:
        """``[L]`` bool: the loop agrees with the optimised trajectory (residual < INLIER_CHI2)."""
        return self.loop_residuals() < INLIER_CHI2

    def _relative(self, a: int, b: int) -> gtsam.Pose3:
        pa, pb = (self._estimate_or_odometry(k) for k in (a, b))
        return pa.between(pb)

    def _estimate_or_odometry(self, index: int) -> gtsam.Pose3:
        key = gtsam.symbol("x", index)
        if self._estimate.exists(key):
            return self._estimate.atPose3(key)
        return self.nodes[index].odom

    # ---- internals -----------------------------------------------------------------------------
    def _far_enough(self, a: gtsam.Pose3, b: gtsam.Pose3) -> bool:
        delta = a.between(b)
        turned = math.degrees(np.linalg.norm(gtsam.Rot3.Logmap(delta.rotation())))
        moved = float(np.linalg.norm(delta.translation()))
        return moved >= self.config.node_spacing_m or turned >= self.config.node_spacing_deg

    def _add_node(self, stamp: float, odom: gtsam.Pose3, prior: bool = False) -> None:
        node = Node(len(self.nodes), stamp, odom)
        key = gtsam.symbol("x", node.key)
        if prior:
            tight = gtsam.noiseModel.Diagonal.Sigmas(np.full(6, 1e-6))
            self._new_factors.add(gtsam.PriorFactorPose3(key, odom, tight))
            self._new_values.insert(key, odom)
        else:
            before = self.nodes[-1]
            delta = before.odom.between(odom)
            self._new_factors.add(gtsam.BetweenFactorPose3(
                gtsam.symbol("x", before.key), key, delta, self._odometry_noise(delta)
            ))  # fmt: skip
            previous = gtsam.symbol("x", before.key)
            start = (self._new_values.atPose3(previous) if self._new_values.exists(previous)
                     else self._estimate.atPose3(previous))  # fmt: skip
            self._new_values.insert(key, start.compose(delta))
        self.nodes.append(node)
        self.counts.nodes += 1

    def _odometry_noise(self, delta: gtsam.Pose3) -> gtsam.noiseModel.Base:
        c = self.config
        metres = float(np.linalg.norm(delta.translation()))
        trans = c.odom_sigma_m + c.odom_sigma_per_m * metres
        rot = math.radians(c.odom_sigma_deg + c.odom_sigma_deg_per_m * metres)
        return gtsam.noiseModel.Diagonal.Sigmas(np.array([rot] * 3 + [trans] * 3))

    def _nearest_node(self, stamp: float) -> Node:
        stamps = self.node_stamps()
        i = int(np.searchsorted(stamps, stamp))
        candidates = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
        return self.nodes[min(candidates, key=lambda j: abs(stamps[j] - stamp))]

    def _anchor(self, stamp: float) -> tuple[Node, gtsam.Pose3] | str:
        """The node nearest to ``stamp`` and the base's pose at ``stamp`` in that node's frame."""
        odom = self.history.pose_at(stamp, self.config.stamp_tolerance_s)
        if isinstance(odom, str):
            return odom
        node = self._nearest_node(stamp)
        return node, node.odom.between(odom)

    def _insert_loop(self, loop: LoopFactor) -> str | None:
        if not self.nodes:
            return "no odometry yet"
        match, query = self._anchor(loop.match_stamp), self._anchor(loop.query_stamp)
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
        width = self.config.loop_kernel_width
        if self.config.innovation_kernel:
            width *= self._drift_scale(match_node.key, query_node.key, measured, cov)
        noise = self._robust(gtsam.noiseModel.Gaussian.Covariance(cov), width)
        self._new_loops += 1
        self._new_factors.add(gtsam.BetweenFactorPose3(
            gtsam.symbol("x", match_node.key), gtsam.symbol("x", query_node.key), measured, noise
        ))  # fmt: skip
        self.loops.append(
            LoopEntry(match_node.key, query_node.key, loop, measured, np.linalg.inv(cov))
        )
        self.counts.loops_added += 1
        return None

    def _drift_scale(
        self, match: int, query: int, measured: gtsam.Pose3, cov: np.ndarray
    ) -> float:
        """How much wider than the loop's own sigma a true loop's residual can be, given how
        uncertain the graph still is about the two nodes' relative pose: the RMS of the residual
        under the innovation covariance S = (relative marginal) + (loop), whitened by the loop's
        covariance, over the 6 dimensions; >= 1."""
        self.update()  # the nodes must be in iSAM2 for their marginals
        a, b = gtsam.symbol("x", match), gtsam.symbol("x", query)
        to_query = measured.inverse().AdjointMap()  # match-frame perturbation -> query frame
        relative = to_query @ self._isam.marginalCovariance(a) @ to_query.T
        relative += self._isam.marginalCovariance(b)  # correlation ignored: errs wide
        ratio = np.trace(np.linalg.solve(cov, relative + cov)) / 6.0
        return float(np.sqrt(max(ratio, 1.0)))

    def _robust(self, noise: gtsam.noiseModel.Base, width: float) -> gtsam.noiseModel.Base:
        kind = self.config.loop_kernel
        if kind == "none":
            return noise
        estimator = (gtsam.noiseModel.mEstimator.Cauchy if kind == "cauchy"
                     else gtsam.noiseModel.mEstimator.Huber).Create(width)  # fmt: skip
        return gtsam.noiseModel.Robust.Create(estimator, noise)

    def _retry_pending(self) -> None:
        latest = self.history.latest_stamp
        ready = [lp for lp in self.pending if max(lp.query_stamp, lp.match_stamp) <= latest]
        if not ready:
            return
        self.pending = [lp for lp in self.pending if max(lp.query_stamp, lp.match_stamp) > latest]
        for loop in ready:
            reason = self._insert_loop(loop)
            if reason is not None:
                self.counts.skipped[f"loop: {_reason_kind(reason)}"] += 1


def _reason_kind(reason: str) -> str:
    """A reason without its details in parentheses, for counting."""
    return reason.split(" (")[0]
