"""Small saved place maps for the map-tool tests (`pairvpr-map`): made in a test's tmp_path."""

from __future__ import annotations

import numpy as np

from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap

DIM, DENSE = 8, (2, 3)


def make_map(path, robot, session, n, seed, fingerprint="model-a", dim=DIM, index="flat"):
    """A saved map of `n` keyframes of robot/session; keyframe 1 has features."""
    rng = np.random.default_rng(seed)
    m = PlaceMap(desc_dim=dim, dense_shape=DENSE, fingerprint=fingerprint, index=index)
    for i in range(n):
        meta = KeyframeMeta(
            stamp=10.0 + i, frame_id="cam", pose=(float(i), 0, 0, 0, 0, 0, 1), source="bag",
            robot=robot, session=session,
        )  # fmt: skip
        dense = rng.normal(size=DENSE).astype(np.float16)
        m.add(rng.normal(size=dim), dense, meta, b"features-%d" % i if i == 1 else b"")
    m.save(path)
    m.close()
    return path


def save_keyframes(path, keyframes) -> str:
    """A saved map of ``keyframes`` [(stamp, pose or None, robot, session)], in that order."""
    rng = np.random.default_rng(0)
    m = PlaceMap(desc_dim=DIM, dense_shape=DENSE, fingerprint="any-model")
    for stamp, pose, robot, session in keyframes:
        meta = KeyframeMeta(stamp=float(stamp), pose=None if pose is None else tuple(pose),
                            robot=robot, session=session, frame_id="cam")  # fmt: skip
        m.add(rng.normal(size=DIM), rng.normal(size=DENSE), meta)
    m.save(path)
    m.close()
    return str(path)


def prior_drive_map(path, drive, trajectory=("a", "day1"), without_pose=()) -> str:
    """Every frame of ``drive`` a keyframe of ``trajectory`` with its odometry pose (the frames
    in ``without_pose`` without one)."""
    rows = [(s, None if i in without_pose else p, *trajectory)
            for i, (s, p) in enumerate(zip(drive[0], drive[2], strict=True))]  # fmt: skip
    return save_keyframes(path, rows)
