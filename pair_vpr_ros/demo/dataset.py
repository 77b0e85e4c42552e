"""Place-recognition training data from the synthetic city: ROOT/<place>/<k>.png.

Each place is a spot in a street, looking along it. Its views move the camera up to 3 m along and
sideways, turn it up to 25 deg, and change the lighting (day, dusk, overcast with jitter) and the
parked cars and people, like the revisits of the demo drive. Place cities come from their own seed
stream, so they never coincide with the demo bag's city.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from pair_vpr_ros.demo.camera import Camera
from pair_vpr_ros.demo.layout import LIGHTINGS, Layout, Lighting, generate_layout, street_occluders
from pair_vpr_ros.demo.render import render_view
from pair_vpr_ros.demo.world import LANE_OFFSET
from pair_vpr_ros.errors import ConfigError, DatasetError

CITY_BLOCKS = 7  # blocks per side of each place city
MIN_VIEWS = 4  # views per place the trainers rely on


def place_poses(layout: Layout, rng: np.random.Generator) -> list[np.ndarray]:
    """Base poses (x, y, yaw) [3], one per inner street segment and direction, shuffled."""
    poses = []
    for lines, across, along_y in ((layout.xs, layout.ys, True), (layout.ys, layout.xs, False)):
        for c in lines[1:-1]:
            for a, b in zip(across[:-1], across[1:], strict=True):
                for sign in (1.0, -1.0):
                    s = (a + b) / 2 + rng.uniform(-0.15, 0.15) * (b - a)
                    yaw = (math.pi / 2 if along_y else 0.0) + (0.0 if sign > 0 else math.pi)
                    d = np.array([math.cos(yaw), math.sin(yaw)])
                    xy = (
                        np.array([c, s]) if along_y else np.array([s, c])
                    ) + LANE_OFFSET * np.array([d[1], -d[0]])
                    poses.append(np.array([xy[0], xy[1], math.atan2(d[1], d[0])]))
    order = rng.permutation(len(poses))
    return [poses[k] for k in order]


def jitter_lighting(base: Lighting, rng: np.random.Generator) -> Lighting:
    """`base` with gain, tint and contrast varied by up to 15 %, 6 % and 10 %."""
    return dataclasses.replace(
        base,
        gain=base.gain * float(rng.uniform(0.85, 1.15)),
        tint=tuple(t * float(rng.uniform(0.94, 1.06)) for t in base.tint),
        contrast=base.contrast * float(rng.uniform(0.9, 1.1)),
    )


def render_place_views(
    layout: Layout, base: np.ndarray, views: int, rng: np.random.Generator, cam: Camera, tag: tuple
) -> list[np.ndarray]:
    """`views` images [H, W, 3] uint8 of the place at `base` (x, y, yaw)."""
    d = np.array([math.cos(base[2]), math.sin(base[2])])
    right = np.array([d[1], -d[0]])
    centre = base[:2] - LANE_OFFSET * right  # kerbs are measured from the street centre line
    out = []
    for k in range(views):
        along, lateral = rng.uniform(-3.0, 3.0), rng.uniform(-3.0, 2.0)
        xy = base[:2] + d * along + right * lateral
        pose = np.array([xy[0], xy[1], base[2] + math.radians(rng.uniform(-25.0, 25.0))])
        lighting = jitter_lighting(LIGHTINGS[k % len(LIGHTINGS)], rng)
        occluders = street_occluders(rng, centre - 20.0 * d, centre + 70.0 * d, keep_clear=2.0)
        out.append(render_view(layout, pose, lighting, occluders, cam, (*tag, k)))
    return out


def write_place_dataset(
    root: str | Path,
    seed: int = 7,
    places: int = 100,
    views_per_place: int = 6,
    size: tuple[int, int] = (320, 240),
    force: bool = False,
    progress: bool = False,
) -> Path:
    """Write `places` folders of `views_per_place` PNG views each under `root`; return `root`.

    The folder is built beside `root` and renamed into place, so a failure leaves nothing behind.
    """
    root = Path(root)
    if seed < 0:
        raise ConfigError(f"seed={seed}: must be >= 0")
    if places < 1:
        raise ConfigError(f"places={places}: need at least 1")
    if views_per_place < MIN_VIEWS:
        raise ConfigError(f"views_per_place={views_per_place}: need at least {MIN_VIEWS}")
    if not all(16 <= v <= 4096 for v in size):
        raise ConfigError(f"image size {size[0]}x{size[1]}: each side must be 16-4096")
    cam = Camera(width=size[0], height=size[1])
    _check_room(root, force)
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{root.name}.", dir=root.parent))
    try:
        _fill(tmp, seed, places, views_per_place, cam, progress)
        if root.exists():  # only now: a failed run keeps the old dataset
            shutil.rmtree(root)
        tmp.replace(root)
    except OSError as err:
        raise DatasetError(f"cannot write place dataset {root}: {err}") from err
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return root


def _fill(folder: Path, seed: int, places: int, views: int, cam: Camera, progress: bool) -> None:
    """Render and save every place; cities are added as the places of one run out."""
    rng = np.random.default_rng([seed, 4])
    bases: list[np.ndarray] = []
    layout: Layout | None = None
    city = 0
    for p in tqdm(range(places), desc="places", unit="place", disable=not progress):
        if not bases:
            city_seed = int(np.random.SeedSequence([seed, 0xDA7A, city]).generate_state(1)[0])
            layout = generate_layout(city_seed, CITY_BLOCKS, CITY_BLOCKS)
            bases = place_poses(layout, rng)
            city += 1
        assert layout is not None
        place_dir = folder / f"place_{p:05d}"
        place_dir.mkdir()
        for k, img in enumerate(
            render_place_views(layout, bases.pop(), views, rng, cam, (seed, p))
        ):
            if not cv2.imwrite(str(place_dir / f"{k}.png"), img[..., ::-1]):
                raise DatasetError(
                    f"cannot write {place_dir / f'{k}.png'}: OpenCV refused the file"
                )


def _check_room(root: Path, force: bool) -> None:
    """Refuse an existing `root` unless `force`, and even then unless it holds only places."""
    if not root.exists():
        return
    if not force:
        raise DatasetError(f"dataset folder {root} already exists; pass --force to overwrite it")
    entries = list(root.iterdir()) if root.is_dir() else [root]
    looks_ok = root.is_dir() and all(
        e.is_dir() and all(f.suffix == ".png" for f in e.iterdir()) for e in entries
    )
    if not looks_ok:
        raise DatasetError(
            f"refusing to overwrite {root}: it is not a place dataset (only <place>/<k>.png "
            "folders); choose another folder"
        )
