"""Odometry as a robot has it: the true drive's increments, read with a scale error, a yaw-rate
bias and noise, and integrated from the true start pose, so it drifts like wheel odometry.

Each step ``i -> i+1`` of the true planar poses is expressed in the body frame at ``i``
(forward, left, turn); the odometry reads ``(1 + scale_error)`` times the translation plus
Gaussian noise of ``translation_noise`` times its length per axis, and the turn plus
``yaw_rate_bias * dt`` plus Gaussian noise of ``yaw_noise_deg``. The noise comes from its own seed
stream, so the world and its images do not change.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.errors import ConfigError


@dataclass(frozen=True)
class OdometryNoise:
    """How the demo's odometry errs. A pose graph cannot see a scale error (a uniformly scaled
    loop still closes), so it bounds the corrected trajectory's ATE from below: about 0.23 m per
    per cent on the demo world (seed 7); the heading drift is what loop closures remove."""

    scale_error: float = 0.015  # travelled distance reads 1.5 % long
    yaw_rate_bias_deg_s: float = 0.5  # the heading turns this much too far left per second
    translation_noise: float = 0.01  # std per axis, as a fraction of the step length
    yaw_noise_deg: float = 0.05  # std of each step's turn

    def validate(self) -> None:
        for name in ("scale_error", "yaw_rate_bias_deg_s", "translation_noise", "yaw_noise_deg"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ConfigError(f"odometry noise: {name}={value!r} must be finite")
        if self.translation_noise < 0 or self.yaw_noise_deg < 0:
            raise ConfigError("odometry noise: noise standard deviations must be >= 0")
        if self.scale_error <= -1:
            raise ConfigError(f"odometry noise: scale_error={self.scale_error} must be > -1")


def drifting_odometry(
    poses: np.ndarray, rate_hz: float, seed: int, noise: OdometryNoise | None = None
) -> np.ndarray:
    """True planar poses ``[N, 3]`` (x, y, yaw) -> drifting odometry poses ``[N, 3]``."""
    noise = noise or OdometryNoise()
    noise.validate()
    poses = np.asarray(poses, dtype=np.float64)
    rng = np.random.default_rng([seed, 4])  # streams 2 and 3 build the world
    n = len(poses)
    step = np.diff(poses[:, :2], axis=0)  # [N-1, 2] world-frame steps
    c, s = np.cos(poses[:-1, 2]), np.sin(poses[:-1, 2])
    forward, left = c * step[:, 0] + s * step[:, 1], -s * step[:, 0] + c * step[:, 1]
    turn = np.angle(np.exp(1j * np.diff(poses[:, 2])))
    length = np.hypot(forward, left)
    sigma = noise.translation_noise * length
    forward = forward * (1 + noise.scale_error) + rng.normal(size=n - 1) * sigma
    left = left * (1 + noise.scale_error) + rng.normal(size=n - 1) * sigma
    turn = (
        turn
        + math.radians(noise.yaw_rate_bias_deg_s) / rate_hz
        + rng.normal(size=n - 1) * math.radians(noise.yaw_noise_deg)
    )
    out = np.empty_like(poses[:, :3])
    out[0] = poses[0, :3]
    for i in range(n - 1):
        x, y, yaw = out[i]
        ci, si = math.cos(yaw), math.sin(yaw)
        out[i + 1] = (x + ci * forward[i] - si * left[i], y + si * forward[i] + ci * left[i],
                      math.remainder(yaw + turn[i], math.tau))  # fmt: skip
    return out
