"""Synthetic fleet drives for pose-graph tests: robots lapping one rectangle on one clock, each
with drifting odometry in its own frame, and loops within and between them."""

from __future__ import annotations

import numpy as np
from drives import CAMERA, RATE, OdometryNoise, drifting_odometry, rectangle_drive

from pair_vpr_ros.posegraph.simulate import trajectory_loops
from pair_vpr_ros.posegraph.transforms import planar_pose7, pose3, pose7


def robot(shift: int, seed: int, laps: int = 2):
    """-> stamps [N], true poses [N, 7] (world frame), odometry [N, 7] in the robot's own frame
    (its start pose is the identity), frames per lap. ``shift``: frames the start is moved
    along the rectangle."""
    truth = np.roll(rectangle_drive(laps), -shift, axis=0)
    odometry = drifting_odometry(truth, RATE, seed=seed, noise=OdometryNoise(0.01, 0.5))
    start = pose3(planar_pose7(*odometry[0])).inverse()
    local = np.array([pose7(start.compose(pose3(planar_pose7(*p)))) for p in odometry])
    stamps = 100.0 + np.arange(len(truth)) / RATE
    return stamps, np.array([planar_pose7(*p) for p in truth]), local, len(truth) // laps


def loops(query, match, query_id, match_id, shift, rng, every=3, start=0, stop=None):
    """Loops from every ``every``-th query frame in ``[start, stop)`` to the match frame 3
    frames further along at the same place; ``shift``: query frame i is at match frame
    i + shift on the rectangle."""
    stamps, _, _, lap = query
    stop = len(stamps) - 3 if stop is None else stop
    pairs = [(stamps[i], match[0][(i + shift) % lap + 3]) for i in range(start, stop, every)]
    return trajectory_loops((query[0], query[1]), (match[0], match[1]), pairs, rng,
                            camera_to_base=CAMERA, query=query_id, match=match_id)  # fmt: skip


def feed(graph, drives: dict, loops_: list) -> None:
    """Odometry of every robot in stamp order, each loop once its query stamp is reached."""
    order = sorted(loops_, key=lambda lp: lp.query_stamp)
    k = 0
    stamps = next(iter(drives.values()))[0]
    for i, stamp in enumerate(stamps):
        for trajectory, drive in drives.items():
            graph.add_odometry(float(stamp), tuple(drive[2][i]), trajectory)
        while k < len(order) and order[k].query_stamp <= stamp:
            graph.add_loop(order[k])
            k += 1
        graph.update()
    graph.finish()


def world_error(graph, trajectory, drive, reference) -> float:
    """RMS position error (m) of a trajectory's optimised nodes against its ground truth moved
    into the map frame (the reference robot's start pose), no alignment."""
    to_map = pose3(reference[1][0]).inverse()
    index = np.searchsorted(drive[0], graph.node_stamps(trajectory))
    truth = np.array([to_map.compose(pose3(drive[1][i])).translation() for i in index])
    est = graph.optimised_poses(trajectory)[:, :3]
    return float(np.sqrt(np.mean(np.sum((est[:, :2] - truth[:, :2]) ** 2, axis=1))))
