"""Settings of ``PoseGraph``: one frozen dataclass, mirrored as posegraph_node parameters."""

from __future__ import annotations

import math
from dataclasses import dataclass

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.posegraph.transforms import valid_pose7

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
    # Several robot-sessions: one joins the graph (is aligned into the first one's frame) once
    # this many of its loops to joined trajectories agree on where it is: a lone false loop
    # between robots cannot place a whole trajectory (1 = join at the first loop).
    join_min_loops: int = 2
    # Two loops agree when the poses they give one node differ by at most this much ...
    join_tolerance_m: float = 2.0
    join_tolerance_deg: float = 5.0
    # ... plus this fraction of the odometry travelled between their two nodes (drift).
    join_tolerance_per_m: float = 0.02

    def validate(self) -> None:
        """Raise ``ConfigError`` naming the first bad setting."""
        positive = ("node_spacing_m", "node_spacing_deg", "odom_sigma_m", "odom_sigma_deg")
        positive += ("loop_kernel_width", "max_odom_gap_s", "relinearize_threshold")
        positive += ("join_tolerance_m", "join_tolerance_deg")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"pose graph: {name}={value!r} must be a positive number")
        nonnegative = ("odom_sigma_per_m", "odom_sigma_deg_per_m", "stamp_tolerance_s")
        for name in (*nonnegative, "join_tolerance_per_m"):
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
        if not 1 <= self.join_min_loops <= 100:
            raise ConfigError(f"pose graph: join_min_loops={self.join_min_loops} must be 1-100")
        reason = valid_pose7(self.camera_to_base)
        if reason is not None:
            raise ConfigError(f"pose graph: camera_to_base: {reason}")
