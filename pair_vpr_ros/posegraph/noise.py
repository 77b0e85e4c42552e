"""Noise models of the graph's factors: odometry sigmas that grow with the step, the robust
kernel of loop factors and its optional widening by the graph's own uncertainty."""

from __future__ import annotations

import math

import gtsam
import numpy as np

from pair_vpr_ros.posegraph.config import PoseGraphConfig


def odometry_noise(delta: gtsam.Pose3, config: PoseGraphConfig) -> gtsam.noiseModel.Base:
    """Diagonal sigmas of an odometry step ``delta``: floor plus a share per metre."""
    metres = float(np.linalg.norm(delta.translation()))
    trans = config.odom_sigma_m + config.odom_sigma_per_m * metres
    rot = math.radians(config.odom_sigma_deg + config.odom_sigma_deg_per_m * metres)
    return gtsam.noiseModel.Diagonal.Sigmas(np.array([rot] * 3 + [trans] * 3))


def robust(
    noise: gtsam.noiseModel.Base, config: PoseGraphConfig, width: float
) -> gtsam.noiseModel.Base:
    """``noise`` wrapped in the configured kernel (``loop_kernel``) of ``width`` sigmas."""
    kind = config.loop_kernel
    if kind == "none":
        return noise
    estimator = (gtsam.noiseModel.mEstimator.Cauchy if kind == "cauchy"
                 else gtsam.noiseModel.mEstimator.Huber).Create(width)  # fmt: skip
    return gtsam.noiseModel.Robust.Create(estimator, noise)


def drift_scale(
    isam: gtsam.ISAM2, match: int, query: int, measured: gtsam.Pose3, cov: np.ndarray
) -> float:
    """How much wider than the loop's own sigma a true loop's residual can be, given how
    uncertain the graph still is about the two nodes' relative pose: the RMS of the residual
    under the innovation covariance S = (relative marginal) + (loop), whitened by the loop's
    covariance, over the 6 dimensions; >= 1. Both nodes must be in ``isam``."""
    to_query = measured.inverse().AdjointMap()  # match-frame perturbation -> query frame
    relative = to_query @ isam.marginalCovariance(match) @ to_query.T
    relative += isam.marginalCovariance(query)  # correlation ignored: errs wide
    ratio = np.trace(np.linalg.solve(cov, relative + cov)) / 6.0
    return float(np.sqrt(max(ratio, 1.0)))
