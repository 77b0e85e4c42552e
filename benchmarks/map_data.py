"""Synthetic place-map descriptors for benchmarks/bench_map.py.

Two kinds of synthetic 512-d descriptors (bench_map.py `--data`):

- ``trajectory``: what a robot's map looks like. Sessions of 10,000 keyframes drive smooth
  random walks (1 m per keyframe) over a square city of `--city-km`; a place's descriptor is a
  smooth random field of its position (random Fourier features at 15 m, 150 m and 1.5 km length
  scales, 60/30/10 % of the variance) plus a per-session appearance offset (a quarter of the
  place signal's variance) and per-frame noise, so consecutive keyframes are near-duplicates,
  sessions form clusters, and routes revisit each other. Queries are revisits: a database
  keyframe's position moved up to 2 m, seen in a new session's appearance.
- ``lowrank``: x = normalise(A z + noise), z ~ N(0, I_64): no trajectory structure at all, an
  unstructured 64-d cloud (the earlier benchmark's data). Queries: database vector + noise.
"""

from __future__ import annotations

import numpy as np


def lowrank(n: int, dim: int, rng: np.random.Generator, basis: np.ndarray) -> np.ndarray:
    """-> [n, dim] float32 unit vectors with intrinsic dimension basis.shape[0]."""
    out = np.empty((n, dim), np.float32)
    for lo in range(0, n, 100_000):
        z = rng.standard_normal((min(n, lo + 100_000) - lo, basis.shape[0]), dtype=np.float32)
        x = z @ basis + 0.05 * rng.standard_normal((len(z), dim), dtype=np.float32)
        out[lo : lo + len(z)] = x / np.linalg.norm(x, axis=1, keepdims=True)
    return out


class City:
    """A smooth random field R^2 -> R^dim over several length scales (random Fourier features:
    a street's look at 15 m, a block's at 150 m, a district's at 1.5 km) and session
    appearances."""

    SCALES = ((15.0, 0.6), (150.0, 0.3), (1500.0, 0.1))  # (length scale m, share of variance)

    def __init__(self, dim: int, km: float, rng: np.random.Generator, features: int = 512):
        self.size = km * 1000.0
        self.fields = [
            (
                rng.standard_normal((2, features)).astype(np.float32) / scale,
                rng.uniform(0, 2 * np.pi, features).astype(np.float32),
                rng.standard_normal((features, dim)).astype(np.float32)
                * np.sqrt(2.0 * share / features),
            )
            for scale, share in self.SCALES
        ]
        self.dim, self.rng = dim, rng

    def describe(self, xy: np.ndarray, session: np.ndarray) -> np.ndarray:
        """positions [n, 2] m, session appearance offsets [n, dim] -> unit descriptors [n, dim]:
        place signal of unit variance per dimension + session offset + per-frame noise."""
        xy = xy.astype(np.float32)
        x = sum(np.cos(xy @ omega + phase) @ mix for omega, phase, mix in self.fields)
        x += session + 0.3 * self.rng.standard_normal(x.shape, dtype=np.float32)
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    def appearance(self) -> np.ndarray:
        """A session's appearance offset (lighting, season): [dim], ~0.5 of the place signal."""
        return 0.5 * self.rng.standard_normal(self.dim).astype(np.float32)

    def drive(self, n: int) -> np.ndarray:
        """A smooth random walk of n keyframes 1 m apart inside the city -> [n, 2] m."""
        heading = np.cumsum(self.rng.normal(0.0, 0.05, n)) + self.rng.uniform(0, 2 * np.pi)
        steps = np.stack([np.cos(heading), np.sin(heading)], axis=1)
        xy = self.rng.uniform(0, self.size, 2) + np.cumsum(steps, axis=0)
        return np.abs((xy + self.size) % (2 * self.size) - self.size)  # reflect at the edges


def trajectory(n: int, dim: int, rng: np.random.Generator, km: float):
    """-> (descriptors [n, dim], positions [n, 2] m, the City): sessions of 10,000 keyframes."""
    city = City(dim, km, rng)
    out, xy_all = np.empty((n, dim), np.float32), np.empty((n, 2), np.float32)
    for lo in range(0, n, 10_000):
        hi = min(n, lo + 10_000)
        xy_all[lo:hi] = xy = city.drive(hi - lo)
        out[lo:hi] = city.describe(xy, city.appearance()[None])
    return out, xy_all, city


def trajectory_queries(city: City, xy: np.ndarray, limit: int, q: int, rng) -> np.ndarray:
    """Revisits of keyframes < `limit`: position moved up to 2 m, a new session's appearance."""
    picks = rng.integers(0, limit, q)
    moved = xy[picks] + rng.uniform(-2.0, 2.0, (q, 2)).astype(np.float32)
    return city.describe(moved, city.appearance()[None])
