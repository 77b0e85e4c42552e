"""Tiny drive maps for the pair-tune tests: hand-placed stamps, positions and descriptor angles,
so that what `drive_pairs.mine_drive` finds is known exactly."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pair_vpr_ros.model import ModelConfig, PairVPR, build_pairvpr, load_pairvpr, save_pairvpr
from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap

# Keyframe k: stamp k s, position (X[k], 0, 0) m, descriptor (cos A[k], sin A[k], 0, ...).
X = [0.0, 100.0, 200.0, 1.0, 1.5, 300.0, 2.0, 5.0]
A = [0.3, 0.05, 1.5, 0.0, 0.0, 0.0, 1.5, 0.0]


def tiny_checkpoint(path: Path) -> tuple[Path, PairVPR]:
    """A random-init tiny Pair-VPR saved to `path` and loaded back (weights_id = its hash)."""
    save_pairvpr(build_pairvpr(ModelConfig.tiny(), seed=0), path)
    return path, load_pairvpr(path)


def write_drive(
    directory: Path,
    model: PairVPR,
    xs: list[float] = X,
    angles: list[float] = A,
    poses: bool = True,
    seed: int = 0,
    fingerprint: str | None = None,
    shape: tuple[int, int] | None = None,
) -> Path:
    """Save a place map of len(xs) keyframes (dense tokens random, float16) to `directory`."""
    rng = np.random.default_rng(seed)
    shape = shape or (model.num_patches, model.config.embed_dim)
    dim = model.config.desc_dim
    print_ = model.fingerprint if fingerprint is None else fingerprint
    with PlaceMap(dim, shape, print_) as pmap:
        for k, (x, a) in enumerate(zip(xs, angles, strict=True)):
            desc = np.zeros(dim, dtype=np.float32)
            desc[:2] = math.cos(a), math.sin(a)
            pose = (x, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0) if poses else None
            dense = rng.standard_normal(shape).astype(np.float32)
            pmap.add(desc, dense, KeyframeMeta(stamp=float(k), pose=pose))
        pmap.save(directory)
    return directory


def loop_drive(laps: int = 3, per_lap: int = 12) -> tuple[list[float], list[float]]:
    """Positions and descriptor angles of `laps` laps of a 120 m line driven back to the start:
    every later lap revisits the first one's places (20 m apart along it) with alike
    descriptors, so each keyframe of lap 2+ has positives and hard negatives."""
    xs, angles = [], []
    for _lap in range(laps):
        for i in range(per_lap):
            xs.append(10.0 * i)
            angles.append(0.1 * i)
    return xs, angles
