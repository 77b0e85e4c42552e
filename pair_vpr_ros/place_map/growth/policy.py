"""The growth policy's rule, shared by the pipeline (loops/growth.py, as keyframes arrive) and
`compact_map` (over a saved map's signatures and links): is a new keyframe Q represented by a
stored one?

Q has accepted loops with a confident pose to keyframes K (T_K_Q each). The candidates are each
K and the keyframes linked to K (one hop). A candidate C represents Q when T_C_Q (the loop's
pose composed with the link's) lies within `max_translation_m` and `max_rotation_deg` and C's
appearance signature lies within `max_appearance` of Q's, and C is no recent keyframe of Q's
own robot-session (`exclude_recent_s`); the closest signature wins.

A Q that is not represented but has such a loop to a K with features within
`share_translation_m` and `share_rotation_deg` (a known place in another light or from another
view) is stored without features: its descriptor and dense tokens find and re-rank it, its
geometry is K's through their link (loops/growth.py, `MapGrowth.feature_source`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.place_map.growth.tables import compose

Pose7 = tuple[float, ...]  # x y z qx qy qz qw
IDENTITY_POSE: Pose7 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class GrowthConfig:
    """When a stored keyframe represents a new one, or lends it its features (module
    docstring). Chosen on the lifelong run's maps (benchmarks/bench_lifelong.py,
    docs/map-storage.md, growth): pairs of one place in one light from other laps lie at
    signature distance 0.002-0.073 (5th-95th percentile), 1.2-5.6 m and 1-24 deg apart; in day
    against dusk light at 0.145-0.182. The demo model re-ranks a revisit 8-11 deg off a stored
    view above its threshold, but often not one 24 deg off: with 30 deg, the third lap's views
    (16 deg off the first) were represented by the first lap's, and the fifth lap (24 deg off
    the first, 8 deg off the third) missed 11 of its 48 queries instead of 5 (lifelong run,
    docs/performance.md)."""

    max_appearance: float = 0.08  # mean absolute signature difference (values in 0..1)
    max_translation_m: float = 6.0
    max_rotation_deg: float = 12.0
    share_translation_m: float = 6.0  # a known place anew: stored without features
    share_rotation_deg: float = 30.0
    # A keyframe of the query's own robot-session this recent never represents it: "already in
    # the map" means an earlier visit, not the last seconds of the drive (the detector's
    # exclude_recent_s, which the pipeline passes; the node's default for compact)
    exclude_recent_s: float = 30.0

    def __post_init__(self) -> None:
        names = ("max_appearance", "max_translation_m", "max_rotation_deg",
                 "share_translation_m", "share_rotation_deg", "exclude_recent_s")  # fmt: skip
        for name in names:
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"growth {name}={value!r} must be a finite number >= 0")

    def near(self, pose: Pose7) -> bool:
        """Is T (x y z qx qy qz qw) within the limits of a representative?"""
        return within(pose, self.max_translation_m, self.max_rotation_deg)

    def shares(self, pose: Pose7) -> bool:
        """Is T within the limits of a keyframe that lends its features?"""
        return within(pose, self.share_translation_m, self.share_rotation_deg)


def within(pose: Pose7, translation_m: float, rotation_deg: float) -> bool:
    """Is T (x y z qx qy qz qw) within `translation_m` and `rotation_deg`?"""
    angle = 2.0 * math.degrees(math.acos(min(1.0, abs(float(pose[6])))))
    distance = math.sqrt(sum(float(v) ** 2 for v in pose[:3]))
    return distance <= translation_m and angle <= rotation_deg


def appearance_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two signatures [S] (inf when their sizes differ)."""
    if a.shape != b.shape:
        return math.inf
    return float(np.mean(np.abs(a - b)))


def find_representative(
    signature: np.ndarray,
    posed: list[tuple[int, Pose7]],
    links: Callable[[int], list[tuple[int, Pose7]]],
    signature_of: Callable[[int], np.ndarray | None],
    config: GrowthConfig,
) -> tuple[int, float] | None:
    """(id, signature distance) of the keyframe that represents Q, None when none does.

    signature [S]: Q's; posed: (K, T_K_Q) of Q's confident loops; links(K): (C, T_C_K) of K's
    links; signature_of(C): C's signature (None: C has none or may not represent it, e.g. a
    recent keyframe of Q's own session: `is_recent`)."""
    best: tuple[int, float] | None = None
    for match_id, t_match_query in posed:
        for other, t_other_match in [(match_id, IDENTITY_POSE), *links(match_id)]:
            if not config.near(compose(t_other_match, t_match_query)):
                continue
            stored = signature_of(other)
            if stored is None:
                continue
            distance = appearance_distance(signature, stored)
            if distance <= config.max_appearance and (best is None or distance < best[1]):
                best = (other, distance)
    return best


def is_recent(
    query: tuple[float, str, str], other: tuple[float, str, str], config: GrowthConfig
) -> bool:
    """Is `other` (stamp, robot, session) a recent keyframe of the query's own robot-session?"""
    same = query[1:] == other[1:]
    return same and abs(query[0] - other[0]) < config.exclude_recent_s
