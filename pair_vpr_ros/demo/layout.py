"""Street-grid layout of the synthetic world: blocks lined with facades, lightings, occluders.

World frame: x east, y north, z up, metres. Streets run along x and y between rectangular blocks;
each block edge is split into buildings whose street-facing facades are vertical rectangles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

ROAD_HALF_WIDTH = 6.0  # m, street centre line to kerb
SIDEWALK_WIDTH = 3.0  # m, kerb to facade
STREET_HALF_WIDTH = ROAD_HALF_WIDTH + SIDEWALK_WIDTH


@dataclass(frozen=True)
class Lighting:
    """Look of one visit: sky and ground colours, fog, and per-channel curves after rendering."""

    name: str
    gain: float = 1.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)  # RGB multipliers
    contrast: float = 1.0  # around mid grey
    gamma: float = 1.0
    sky_top: tuple[int, int, int] = (70, 130, 215)
    sky_horizon: tuple[int, int, int] = (185, 210, 235)
    road: tuple[int, int, int] = (92, 92, 96)
    sidewalk: tuple[int, int, int] = (160, 156, 148)
    fog_colour: tuple[int, int, int] = (190, 205, 220)
    fog_distance: float = 160.0  # m; fog weight = 1 - exp(-depth / fog_distance)
    sun: tuple[float, float] = (
        0.6,
        0.8,
    )  # horizontal direction towards the sun, for facade shading


DAY = Lighting("day")
DUSK = Lighting(
    "dusk",
    gain=0.62,
    tint=(1.12, 0.9, 0.78),
    contrast=0.8,
    gamma=1.15,
    sky_top=(45, 50, 110),
    sky_horizon=(235, 140, 85),
    road=(70, 66, 72),
    sidewalk=(120, 110, 110),
    fog_colour=(170, 120, 110),
    fog_distance=120.0,
    sun=(-0.95, 0.3),
)
OVERCAST = Lighting(
    "overcast",
    gain=0.9,
    tint=(0.97, 1.0, 1.05),
    contrast=0.72,
    gamma=0.95,
    sky_top=(150, 155, 165),
    sky_horizon=(205, 208, 212),
    road=(100, 100, 102),
    sidewalk=(150, 150, 150),
    fog_colour=(200, 202, 206),
    fog_distance=110.0,
    sun=(0.0, -1.0),
)
LIGHTINGS = (DAY, DUSK, OVERCAST)


@dataclass(frozen=True)
class Facade:
    """A street-facing building front; p0 -> p1 runs left to right as seen from the street."""

    id: int
    p0: tuple[float, float]
    p1: tuple[float, float]
    height: float
    block: int

    @property
    def length(self) -> float:
        return math.hypot(self.p1[0] - self.p0[0], self.p1[1] - self.p0[1])


@dataclass(frozen=True)
class Occluder:
    """A car (box, length x width x height) or a person (billboard) standing in the street."""

    kind: str  # "car" | "person"
    x: float
    y: float
    yaw: float
    colour: tuple[int, int, int]
    size: tuple[float, float, float]


@dataclass(eq=False)
class Layout:
    """Street grid: centre lines `xs` [nx+1], `ys` [ny+1]; `blocks` [B, 4] (x0, y0, x1, y1)."""

    seed: int
    xs: np.ndarray
    ys: np.ndarray
    blocks: np.ndarray
    facades: list[Facade]
    cache: dict = field(default_factory=dict, repr=False)  # renderer arrays and textures


def generate_layout(seed: int, nx: int, ny: int) -> Layout:
    """Street spacing 38-62 m, building widths 7-16 m and heights 7-30 m, random from `seed`."""
    rng = np.random.default_rng([seed, 1])
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(38.0, 62.0, nx))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(38.0, 62.0, ny))])
    blocks, facades = [], []
    for j in range(ny):
        for i in range(nx):
            x0, x1 = xs[i] + STREET_HALF_WIDTH, xs[i + 1] - STREET_HALF_WIDTH
            y0, y1 = ys[j] + STREET_HALF_WIDTH, ys[j + 1] - STREET_HALF_WIDTH
            b = len(blocks)
            blocks.append((x0, y0, x1, y1))
            # CCW walk: left to right as seen from outside, outward normal on the right.
            corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
            for k in range(4):
                a, c = np.array(corners[k]), np.array(corners[(k + 1) % 4])
                for t0, t1 in _split(rng, float(np.linalg.norm(c - a))):
                    p0, p1 = a + (c - a) * t0, a + (c - a) * t1
                    facades.append(
                        Facade(
                            id=len(facades),
                            p0=(float(p0[0]), float(p0[1])),
                            p1=(float(p1[0]), float(p1[1])),
                            height=float(rng.uniform(7.0, 30.0)),
                            block=b,
                        )
                    )
    return Layout(seed, xs, ys, np.array(blocks, dtype=np.float64), facades)


def _split(rng: np.random.Generator, length: float) -> list[tuple[float, float]]:
    """Cut an edge of `length` m into building widths of 7-16 m -> [(t0, t1)] fractions."""
    cuts, pos = [0.0], 0.0
    while length - pos > 16.0:
        pos += float(rng.uniform(7.0, min(16.0, length - pos - 7.0)))
        cuts.append(pos)
    cuts.append(length)
    return [(a / length, b / length) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]


CAR_COLOURS = (
    (200, 30, 30),
    (240, 240, 240),
    (25, 25, 30),
    (150, 155, 165),
    (30, 70, 170),
    (230, 190, 30),
    (20, 120, 60),
    (120, 30, 110),
)


def street_occluders(
    rng: np.random.Generator, a: np.ndarray, b: np.ndarray, keep_clear: float = 12.0
) -> list[Occluder]:
    """Parked cars on both kerbs and people on both sidewalks of the street from `a` to `b` [2]."""
    d = b - a
    length = float(np.linalg.norm(d))
    d = d / length
    right = np.array([d[1], -d[0]])
    yaw = math.atan2(d[1], d[0])
    out: list[Occluder] = []
    for side in (1.0, -1.0):
        for s in np.arange(keep_clear, length - keep_clear, 7.5):
            if rng.random() < 0.4:
                p = a + d * (s + rng.uniform(-1.0, 1.0)) + right * side * (ROAD_HALF_WIDTH - 1.0)
                colour = CAR_COLOURS[int(rng.integers(len(CAR_COLOURS)))]
                size = (float(rng.uniform(3.8, 4.8)), 1.8, float(rng.uniform(1.4, 1.9)))
                out.append(Occluder("car", float(p[0]), float(p[1]), yaw, colour, size))
        for _ in range(int(rng.integers(0, max(1, int(length / 12))))):
            s = rng.uniform(keep_clear / 2, length - keep_clear / 2)
            lat = side * (ROAD_HALF_WIDTH + rng.uniform(0.7, SIDEWALK_WIDTH - 0.6))
            p = a + d * s + right * lat
            colour = tuple(int(c) for c in rng.integers(20, 236, 3))
            size = (0.5, 0.5, float(rng.uniform(1.55, 1.9)))
            out.append(Occluder("person", float(p[0]), float(p[1]), yaw, colour, size))
    return out
