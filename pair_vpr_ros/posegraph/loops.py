"""Loop closures as the pose graph takes them: ``messages.factor.LoopFactor`` (the record
vpr_node and the replay publish), checked and moved from the camera frames into the graph's nodes.

A ``LoopFactor`` holds ``T_match_query`` (the query camera's pose in the match camera's frame)
and its covariance; ``LoopFactor.gtsam_covariance()`` gives it in GTSAM's order and frame
(rx, ry, rz, x, y, z; right perturbation in the query camera frame), which is what the graph uses.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import gtsam
import numpy as np

from pair_vpr_ros.identity import name_problem
from pair_vpr_ros.messages.factor import IDENTITY, LoopFactor
from pair_vpr_ros.posegraph.transforms import valid_pose7

MAX_TRANSLATION_M = 1e5  # a loop's translation beyond this (100 km) is damage, not a loop


@dataclass(eq=False)
class LoopEntry:
    """A loop placed between two graph nodes: their gtsam keys, the factor it came from, the
    measured relative pose between the nodes' base frames, the inverse of its covariance and
    the (robust) noise model of its between-factor."""

    match_key: int
    query_key: int
    factor: LoopFactor
    measured: gtsam.Pose3
    information: np.ndarray  # [6, 6], GTSAM order
    noise: gtsam.noiseModel.Base | None = None

    def between(self) -> gtsam.BetweenFactorPose3:
        return gtsam.BetweenFactorPose3(self.match_key, self.query_key, self.measured, self.noise)


def loop_problem(factor: LoopFactor) -> str | None:
    """Why the pose graph cannot use ``factor`` (None when it can)."""
    if not (np.isfinite(factor.query_stamp) and np.isfinite(factor.match_stamp)):
        return "stamp is not finite"
    reason = valid_pose7((*factor.translation, *factor.rotation))
    if reason is not None:
        return f"transform: {reason}"
    length = float(np.linalg.norm(np.asarray(factor.translation, dtype=np.float64)))
    if length > MAX_TRANSLATION_M:  # finite, but no camera moved that far: GTSAM fails on it
        return f"transform: translation beyond {MAX_TRANSLATION_M:.0e} m ({length:.3g} m)"
    for name in IDENTITY:
        value = getattr(factor, name)
        if value and name_problem(name, value):
            return f"{name} is no valid robot or session id ({value!r})"
    cov = np.asarray(factor.covariance, dtype=np.float64)
    if cov.size != 36:
        return f"covariance needs 36 values (got {cov.size})"
    cov = cov.reshape(6, 6)
    if not np.isfinite(cov).all():
        return "covariance has NaN or infinite values"
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12):
        return "covariance is not symmetric"
    if np.linalg.eigvalsh(cov).min() <= 0.0:
        return "covariance is not positive definite"
    return None


def camera_pose(factor: LoopFactor) -> gtsam.Pose3:
    """``T_match_query`` as a ``gtsam.Pose3``."""
    qx, qy, qz, qw = (float(v) for v in factor.rotation)
    norm = float(np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw))
    rot = gtsam.Rot3.Quaternion(qw / norm, qx / norm, qy / norm, qz / norm)
    return gtsam.Pose3(rot, np.asarray(factor.translation, dtype=np.float64))


def own(factor: LoopFactor, owner: tuple[str, str]) -> LoopFactor:
    """``factor`` with the ends that name no robot and session given to ``owner``."""
    names = {}
    for side in ("query", "match"):
        if not getattr(factor, f"{side}_robot") and not getattr(factor, f"{side}_session"):
            names[f"{side}_robot"], names[f"{side}_session"] = owner
    return replace(factor, **names) if names else factor
