"""Recall by the way a revisit was driven (issue 49): the same way as before, or the other way.

A forward camera driving a street back the other way sees other facades than it saw, and misses
most of those revisits; a rear camera sees them as the forward camera did. So a replay with
ground truth (headings included) splits its recall:

* an **instant** is the keyframes of one stamp (a rig keyframe: every camera's, within
  ``tolerance`` s; one keyframe for a single camera), placed at its ground-truth pose;
* instant q's **true matches** are the earlier instants with a stored keyframe, at least
  ``exclusion_s`` away in time and within ``gt_radius`` m (as `loop_truth` judges a loop);
* q is a revisit driven **the other way** when no true match's heading lies within 90 deg of
  q's, else **the same way**;
* an instant **got a true loop** when any of its keyframes' accepted loops is true
  (`loop_truth.is_true_loop`); recall = such instants / the instants of that kind.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from pair_vpr_ros.messages.loop import same_session
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo, KeyframeLookup, is_true_loop

OPPOSITE_DEG = 90.0  # a true match further than this from the query's heading: the other way


def _yaw(pose: Sequence[float]) -> float:
    """Heading (rad) of a pose's quaternion about z."""
    qx, qy, qz, qw = pose[3:7]
    return math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))


def _instants(keyframes: Sequence[KeyframeInfo], tolerance: float) -> list[list[KeyframeInfo]]:
    """Posed keyframes grouped by stamp (a group: stamps within `tolerance` of its first)."""
    out: list[list[KeyframeInfo]] = []
    for k in sorted((k for k in keyframes if k.pose is not None), key=lambda k: k.stamp):
        if out and k.stamp - out[-1][0].stamp <= tolerance:
            out[-1].append(k)
        else:
            out.append([k])
    return out


def direction_recall(
    records: Sequence[Any],
    keyframes: Sequence[KeyframeInfo],
    gt_radius: float,
    exclusion_s: float,
    tolerance: float = 0.05,
) -> dict[str, Any] | None:
    """``{"same": {...}, "opposite": {...}}``, each ``positives``, ``found`` and ``recall``
    (None without revisits of that kind); None when no keyframe has a pose."""
    groups = _instants(keyframes, tolerance)
    if not groups:
        return None
    xyz = np.array([g[0].pose[:3] for g in groups], dtype=np.float64)
    yaw = np.array([_yaw(g[0].pose) for g in groups])
    stamps = np.array([g[0].stamp for g in groups])
    stored = np.array([any(k.stored for k in g) for g in groups])
    cells: dict[tuple[int, ...], list[int]] = {}
    for i, p in enumerate(xyz):
        cells.setdefault(tuple(np.floor(p / gt_radius).astype(int)), []).append(i)
    kind = np.full(len(groups), "", dtype=object)  # "" no revisit, "same", "opposite"
    for q, p in enumerate(xyz):
        cell = np.floor(p / gt_radius).astype(int)
        near = [i for d in np.ndindex(3, 3, 3)
                for i in cells.get(tuple(cell + np.array(d) - 1), ())]  # fmt: skip
        near = np.array([i for i in near if i < q], dtype=np.int64)
        if not len(near):
            continue
        ok = (stored[near] & (np.abs(stamps[q] - stamps[near]) >= exclusion_s)
              & (np.linalg.norm(xyz[near] - p, axis=1) <= gt_radius))  # fmt: skip
        if ok.any():
            turn = np.abs(np.angle(np.exp(1j * (yaw[near[ok]] - yaw[q]))))
            kind[q] = "same" if (turn <= math.radians(OPPOSITE_DEG)).any() else "opposite"
    lookup, found = KeyframeLookup(keyframes), set()
    instant_of = {k.stamp: i for i, g in enumerate(groups) for k in g}
    for r in (r for r in records if r.accepted and same_session(r)):  # this run's own loops
        if is_true_loop(lookup.query(r), lookup.match(r), gt_radius, exclusion_s):
            found.add(instant_of.get(r.query_stamp))
    out: dict[str, Any] = {"tolerance_s": tolerance, "opposite_deg": OPPOSITE_DEG}
    for name in ("same", "opposite"):
        members = {i for i in range(len(groups)) if kind[i] == name}
        hit = len(members & found)
        out[name] = {"positives": len(members), "found": hit,
                     "recall": hit / len(members) if members else None}  # fmt: skip
    return out
