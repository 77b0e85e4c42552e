"""The demo fleet: robots driving the demo world's loop on one clock, and a second session.

One world (seed, 3 laps of its loop) is driven by three robots, each from another point of the
loop (a third of a drive apart) for ``frames`` frames, all starting at the same time: their
routes overlap and so do their clocks. Robot ``a`` comes back the next day (clock + 24 h) for a
second session in dusk light, driving the last stretch of the world's drive. Each drive
keeps the lane offsets, parked cars and people of the world's laps it passes, its own odometry
drift and image noise (its own seed), and its odometry starts at the origin of its own frame, as
a robot's does: only the pose graph can put them in one frame. Ground truth: the world frame.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pair_vpr_ros.demo.bag import write_world_bag
from pair_vpr_ros.demo.layout import DAY, DUSK, OVERCAST, Lighting
from pair_vpr_ros.demo.odometry import OdometryNoise
from pair_vpr_ros.demo.world import World, generate_world
from pair_vpr_ros.errors import ConfigError

DAY_NS = 86_400 * 10**9


@dataclass(frozen=True)
class FleetDrive:
    """One robot-session of the fleet: where on the world's drive it starts (a fraction of
    ``frames``), its light in each lap of the world's drive and how many days after the first
    session it drives."""

    robot: str
    session: str
    start: float
    lightings: tuple[Lighting, Lighting, Lighting]
    day: int = 0

    @property
    def name(self) -> str:
        return f"{self.robot}_{self.session}"


# Each robot's light changes from lap to lap, another order for each: the demo model was trained
# on views of a place in different lights and rejects a revisit in the same light (measured: robot
# a in day light on both laps, 0 loops of 112 keyframes with a true match, pair scores ~-1.94).
FLEET = (
    FleetDrive("a", "day1", 0.0, (DAY, DUSK, OVERCAST)),
    FleetDrive("b", "day1", 1 / 3, (DUSK, OVERCAST, DAY)),
    FleetDrive("c", "day1", 2 / 3, (OVERCAST, DAY, DUSK)),
    FleetDrive("a", "day2", 1.0, (DUSK,) * 3, day=1),
)


def fleet_worlds(
    seed: int = 7, frames: int = 300, size: tuple[int, int] = (320, 240)
) -> list[tuple[FleetDrive, World]]:
    """The world of each fleet drive, ``frames`` frames each (the shared world: 2 x frames)."""
    if frames < 24:
        raise ConfigError(f"fleet: frames={frames} per drive must be at least 24")
    world = generate_world(seed, frames=2 * frames, laps=3, width=size[0], height=size[1])
    out = []
    for k, drive in enumerate(FLEET):
        index = (round(drive.start * frames) + np.arange(frames)) % world.num_frames
        start_ns = int(world.stamps_ns[0]) + drive.day * DAY_NS
        out.append((drive, dataclasses.replace(
            world, seed=seed * 1000 + k + 1, poses=world.poses[index],
            stamps_ns=start_ns + (world.stamps_ns[:frames] - world.stamps_ns[0]),
            lap=world.lap[index], revisit_of=np.full(frames, -1, dtype=np.int64),
            lightings=drive.lightings,
        )))  # fmt: skip
    return out


def write_fleet_bags(
    out_dir: str | Path,
    seed: int = 7,
    frames: int = 300,
    size: tuple[int, int] = (320, 240),
    force: bool = False,
    progress: bool = False,
    odometry: OdometryNoise | None = None,
) -> Path:
    """Write each fleet drive as ``out_dir/<robot>_<session>.mcap`` (image, camera_info, depth,
    drifting ``/odom`` from the origin, ``/ground_truth``) and ``out_dir/fleet.json`` listing
    them in order (robot, session, bag, lighting, first stamp); returns the json's path."""
    out_dir = Path(out_dir)
    entries = []
    for drive, world in fleet_worlds(seed, frames, size):
        path = out_dir / f"{drive.name}.mcap"
        write_world_bag(world, path, force=force, progress=progress, odometry=odometry,
                        local_odometry=True)  # fmt: skip
        entries.append({"robot": drive.robot, "session": drive.session, "bag": path.name,
                        "lightings": [light.name for light in drive.lightings], "frames": frames,
                        "first_stamp": float(world.stamps[0])})  # fmt: skip
    manifest = out_dir / "fleet.json"
    manifest.write_text(json.dumps({"seed": seed, "drives": entries}, indent=1) + "\n")
    return manifest
