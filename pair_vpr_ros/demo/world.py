"""The demo world: a seeded street grid and a camera that drives the same block loop several times.

Lap 0 is the first visit (day, right lane, camera straight ahead). Every later lap is a revisit
with a lateral offset of 1-3 m, a heading offset of 10-25 deg, another lighting and other parked
cars and people, so each lap after the first gives one set of loop closures. Laps named in
`WorldConfig.reverse_laps` go round the other way, in the other lane (a U-turn where they start
and end): a forward camera sees their streets from the other side; a rear camera sees them as
lap 0's forward camera did (demo/rig.py).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.demo.layout import (
    LIGHTINGS,
    Layout,
    Lighting,
    Occluder,
    generate_layout,
    street_occluders,
)
from pair_vpr_ros.errors import ConfigError

LANE_OFFSET = 1.5  # m right of the street centre line (right-hand traffic)
CORNER_RADIUS = 10.0  # m, turning radius of the centre line at corners
MARGIN_BLOCKS = 2  # blocks of city around the loop, so views down a street are not empty
REVISIT_RADIUS = 6.0  # m; a later-lap frame this close to a first-lap frame is its revisit


@dataclass(frozen=True)
class WorldConfig:
    """Trajectory and image settings of `generate_world` (defaults: 480 frames, 48 s, 3 laps)."""

    frames: int = 480  # camera frames in the whole drive
    rate_hz: float = 10.0  # frame rate
    laps: int = 3  # laps of the loop; laps - 1 revisits (loops)
    width: int = 320  # image width, px
    height: int = 240  # image height, px
    speed: float = 9.0  # m/s wanted; the loop size is picked for it, then it is fitted exactly
    start_time: float = 1_700_000_000.0  # s, stamp of frame 0
    reverse_laps: tuple[int, ...] = ()  # laps driven the other way round (1 .. laps - 1)

    def validate(self) -> None:
        """Raise ConfigError for values the generator cannot honour."""
        if self.laps < 2:
            raise ConfigError(f"laps={self.laps}: need at least 2 laps for a revisit")
        if self.frames < 8 * self.laps:
            raise ConfigError(f"frames={self.frames}: need at least 8 per lap ({8 * self.laps})")
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise ConfigError(f"image size {self.width}x{self.height}: each side must be 16-4096")
        if self.rate_hz <= 0 or self.speed <= 0:
            raise ConfigError(f"rate_hz={self.rate_hz}, speed={self.speed}: must be positive")
        if not all(isinstance(k, int) and 1 <= k < self.laps for k in self.reverse_laps):
            raise ConfigError(
                f"reverse_laps={self.reverse_laps}: each a lap in 1..{self.laps - 1}"
            )


@dataclass(eq=False)
class World:
    """Layout plus trajectory. Arrays have one row per frame (N = config.frames)."""

    seed: int
    config: WorldConfig
    layout: Layout
    poses: np.ndarray  # [N, 3] x, y (m), yaw (rad, from +x towards +y) of the camera
    stamps_ns: np.ndarray  # [N] int64 header stamps
    lap: np.ndarray  # [N] int, 0 = first visit
    revisit_of: np.ndarray  # [N] int, nearest first-lap frame for later laps, -1 otherwise
    lightings: tuple[Lighting, ...]  # one per lap
    occluders: tuple[tuple[Occluder, ...], ...]  # one set per lap
    lap_offsets: np.ndarray  # [laps, 2] lateral offset (m), heading offset (rad) of each lap
    speed: float  # m/s actually driven
    lap_length: float  # m, centre line length of the loop

    @property
    def num_frames(self) -> int:
        return len(self.poses)

    @property
    def stamps(self) -> np.ndarray:
        """[N] float64 seconds."""
        return self.stamps_ns.astype(np.float64) * 1e-9

    @property
    def loops(self) -> int:
        """Number of revisiting laps."""
        return self.config.laps - 1

    def lighting_of(self, i: int) -> Lighting:
        return self.lightings[int(self.lap[i])]

    def occluders_of(self, i: int) -> tuple[Occluder, ...]:
        return self.occluders[int(self.lap[i])]

    def revisit_pairs(self) -> list[tuple[int, int]]:
        """[(later frame, first-visit frame)] for every revisiting frame."""
        return [(int(i), int(j)) for i, j in enumerate(self.revisit_of) if j >= 0]


def generate_world(seed: int, config: WorldConfig | None = None, **overrides: object) -> World:
    """Deterministic world for `seed`; `overrides` replace WorldConfig fields (frames=60, ...)."""
    config = config or WorldConfig()
    if overrides:
        try:
            config = dataclasses.replace(config, **overrides)
        except TypeError as err:
            raise ConfigError(f"generate_world: unknown setting in {sorted(overrides)}") from err
    config.validate()
    if seed < 0:
        raise ConfigError(f"seed={seed}: must be >= 0")
    rng = np.random.default_rng([seed, 2])
    nbx, nby = _loop_blocks(config, rng)
    layout = generate_layout(seed, nbx + 2 * MARGIN_BLOCKS, nby + 2 * MARGIN_BLOCKS)
    xs, ys = layout.xs[MARGIN_BLOCKS:], layout.ys[MARGIN_BLOCKS:]
    corners = np.array([(xs[0], ys[0]), (xs[nbx], ys[0]), (xs[nbx], ys[nby]), (xs[0], ys[nby])])
    corners = np.roll(corners, -int(rng.integers(4)), axis=0)  # start on any side
    if rng.random() < 0.5:
        corners = corners[::-1].copy()  # clockwise: right turns
    offsets = _lap_offsets(config.laps, rng)
    poses, lap, lap_length = _drive(config, corners, offsets)
    start_ns = int(round(config.start_time * 1e9))
    steps = np.arange(config.frames) / config.rate_hz
    occ_rng = np.random.default_rng([seed, 3])
    edges = [(corners[k], corners[(k + 1) % 4]) for k in range(4)]
    occluders = tuple(
        tuple(o for a, b in edges for o in street_occluders(occ_rng, a, b))
        for _ in range(config.laps)
    )
    return World(
        seed=seed,
        config=config,
        layout=layout,
        poses=poses,
        stamps_ns=start_ns + np.round(steps * 1e9).astype(np.int64),
        lap=lap,
        revisit_of=_revisits(poses, lap),
        lightings=tuple(LIGHTINGS[k % len(LIGHTINGS)] for k in range(config.laps)),
        occluders=occluders,
        lap_offsets=offsets,
        speed=config.laps * lap_length * config.rate_hz / config.frames,
        lap_length=lap_length,
    )


def _drive(
    config: WorldConfig, corners: np.ndarray, offsets: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Camera poses [N, 3], lap index [N] and lap length (m) of `laps` laps around `corners`."""
    path_xy, path_yaw, path_s = _rounded_loop(corners, CORNER_RADIUS)
    lap_length = float(path_s[-1])
    # Integer lap arithmetic keeps lap boundaries exact (frame k * frames / laps starts lap k).
    index = np.arange(config.frames)
    lap = index * config.laps // config.frames
    s = (index * config.laps / config.frames - lap) * lap_length
    lateral, heading = _ramped(offsets, lap, s, ramp=min(25.0, lap_length / 4))
    back = np.isin(lap, config.reverse_laps)  # the other way round: the path from its end
    s = np.where(back, lap_length - s, s)
    tangent = np.interp(s, path_s, path_yaw) + np.where(back, math.pi, 0.0)
    right = LANE_OFFSET + lateral  # m to the right of the centre line
    poses = np.stack(
        [
            np.interp(s, path_s, path_xy[:, 0]) + right * np.sin(tangent),
            np.interp(s, path_s, path_xy[:, 1]) - right * np.cos(tangent),
            np.angle(np.exp(1j * (tangent + heading))),
        ],
        axis=1,
    )
    return poses, lap, lap_length


def _loop_blocks(config: WorldConfig, rng: np.random.Generator) -> tuple[int, int]:
    """Blocks (x, y) of the loop rectangle whose length best fits one lap at the wanted speed."""
    want = config.frames / config.rate_hz * config.speed / config.laps
    options = [(1, 1), (2, 1), (1, 2), (2, 2), (3, 2), (2, 3)]
    # 50 m mean street spacing; rounding the 4 corners saves (2 - pi / 2) * radius each.
    cost = [abs(2 * (a + b) * 50.0 - 1.72 * CORNER_RADIUS - want) for a, b in options]
    best = min(cost)
    near = [o for o, c in zip(options, cost, strict=True) if c <= best + 1e-9]
    return near[int(rng.integers(len(near)))]


def _rounded_loop(corners: np.ndarray, radius: float, ds: float = 0.1) -> tuple[np.ndarray, ...]:
    """Closed path through rectangle `corners` [4, 2] with arcs at the corners, from the middle of
    the first edge -> points [M, 2], unwrapped tangent yaw [M], arclength [M]."""
    pieces = []
    for k in range(4):
        a, b, c = corners[k], corners[(k + 1) % 4], corners[(k + 2) % 4]
        d_in = (b - a) / np.linalg.norm(b - a)
        d_out = (c - b) / np.linalg.norm(c - b)
        start = (a + b) / 2 if k == 0 else a + d_in * radius
        end = b - d_in * radius
        n = max(2, int(np.linalg.norm(end - start) / ds))
        pieces.append(start + np.linspace(0, 1, n, endpoint=False)[:, None] * (end - start))
        phi = np.linspace(0, math.pi / 2, max(2, int(radius * math.pi / 2 / ds)), endpoint=False)
        centre = end + d_out * radius
        pieces.append(
            centre - np.outer(np.cos(phi), d_out) * radius + np.outer(np.sin(phi), d_in) * radius
        )
    pieces.append(((corners[0] + corners[1]) / 2)[None])
    pts = np.concatenate(pieces)
    step = np.diff(pts, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(step[:, 0], step[:, 1]))])
    yaw = np.unwrap(np.arctan2(step[:, 1], step[:, 0]))
    yaw = np.concatenate([yaw, yaw[-1:]])
    return pts, yaw, s


def _lap_offsets(laps: int, rng: np.random.Generator) -> np.ndarray:
    """[laps, 2]: per revisit a lateral offset of 1-3 m (on the road) and a heading offset of
    10-25 deg; lap 0 has none."""
    out = np.zeros((laps, 2))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    for k in range(1, laps):
        lateral = float(rng.uniform(1.0, 3.0))
        lat_sign = -1.0 if lateral > 2.0 else (1.0 if rng.random() < 0.5 else -1.0)
        heading = math.radians(rng.uniform(10.0, 25.0))
        out[k] = (lat_sign * lateral, sign * heading)
        sign = -sign
    return out


def _ramped(
    offsets: np.ndarray, lap: np.ndarray, s: np.ndarray, ramp: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame (lateral, heading) [N] each: a lap eases in from the last lap's over `ramp` m."""
    prev = offsets[np.maximum(lap - 1, 0)]
    cur = offsets[lap]
    w = 0.5 - 0.5 * np.cos(np.pi * np.clip(s / ramp, 0.0, 1.0))
    w = np.where(lap == 0, 1.0, w)
    mix = prev + (cur - prev) * w[:, None]
    return mix[:, 0], mix[:, 1]


def _revisits(poses: np.ndarray, lap: np.ndarray) -> np.ndarray:
    """[N] nearest first-lap frame within REVISIT_RADIUS for frames of later laps, else -1."""
    first = np.flatnonzero(lap == 0)
    out = np.full(len(poses), -1, dtype=np.int64)
    for i in np.flatnonzero(lap > 0):
        d = np.hypot(*(poses[first, :2] - poses[i, :2]).T)
        j = int(np.argmin(d))
        if d[j] <= REVISIT_RADIUS:
            out[i] = first[j]
    return out
