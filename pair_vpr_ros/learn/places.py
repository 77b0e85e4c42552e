"""Place collections for training (``load_places("KIND:ROOT")``): gsv, folders, gldv2, sfxl.

The layouts each loader expects are described in :mod:`pair_vpr_ros.learn`.
"""

from __future__ import annotations

import csv
import math
import os
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from pair_vpr_ros.errors import DatasetError
from pair_vpr_ros.learn.image_files import list_images, parse_utm_name, require_dir

GSV_COLUMNS = ("place_id", "year", "month", "northdeg", "city_id", "lat", "lon", "panoid")
GSV_LAYOUT = "ROOT/Dataframes/<City>.csv and ROOT/Images/<city_id>/<city_id>_<place_id:07d>_...jpg"
FOLDERS_LAYOUT = "ROOT/<place_name>/*.{png,jpg,jpeg,bmp,tif,tiff,webp} (one subfolder per place)"
GLDV2_LAYOUT = (
    "ROOT/train.csv (id,url,landmark_id) or ROOT/train_clean.csv + ROOT/train/a/b/c/abc...jpg"
)
SFXL_LAYOUT = "images named @easting@northing@zone@letter@lat@lon@pano@tile@heading@... under ROOT"


@dataclass(frozen=True)
class PlaceCollection:
    """Images grouped by place; ``places[i]`` holds the image paths of place (label) ``i``."""

    name: str
    places: tuple[tuple[Path, ...], ...]
    skipped_images: int = 0

    def __len__(self) -> int:
        return len(self.places)

    @property
    def num_images(self) -> int:
        return sum(len(p) for p in self.places)


def concat_collections(collections: Sequence[PlaceCollection]) -> PlaceCollection:
    """Join collections; place labels are renumbered consecutively in the given order."""
    return PlaceCollection(
        name="+".join(c.name for c in collections),
        places=tuple(p for c in collections for p in c.places),
        skipped_images=sum(c.skipped_images for c in collections),
    )


def _finish(
    name: str, groups: Iterable[list[Path]], min_images: int, layout: str, root: Path, skipped: int
) -> PlaceCollection:
    places = tuple(tuple(sorted(g)) for g in groups if len(g) >= min_images)
    if not places:
        raise DatasetError(
            f"no place with >= {min_images} images found under {root}; expected layout: {layout}"
        )
    return PlaceCollection(name=name, places=places, skipped_images=skipped)


def load_place_folders(root: str | Path, min_images: int = 2) -> PlaceCollection:
    """``ROOT/<place>/<image>``; places with fewer than ``min_images`` are dropped."""
    root = require_dir(Path(root), FOLDERS_LAYOUT)
    subdirs = sorted(p for p in root.iterdir() if p.is_dir())
    if not subdirs:
        raise DatasetError(f"{root} has no place subfolders; expected layout: {FOLDERS_LAYOUT}")
    groups = [list_images(d) for d in subdirs]
    return _finish(f"folders:{root.name}", groups, min_images, FOLDERS_LAYOUT, root, 0)


def gsv_image_name(row: dict[str, str]) -> str:
    """GSV-Cities file name of one Dataframes row (see the module docstring)."""
    return (
        f"{row['city_id']}_{int(row['place_id']):07d}_{int(row['year']):04d}_"
        f"{int(row['month']):02d}_{int(row['northdeg']):03d}_{float(row['lat'])}_"
        f"{float(row['lon'])}_{row['panoid']}.jpg"
    )


def _read_gsv_city(root: Path, csv_path: Path) -> tuple[list[list[Path]], int]:
    groups: dict[str, list[Path]] = defaultdict(list)
    skipped = 0
    listings: dict[Path, set[str]] = {}
    try:
        with csv_path.open(newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            missing = [c for c in GSV_COLUMNS if c not in (reader.fieldnames or [])]
            if missing:
                raise DatasetError(
                    f"{csv_path} lacks columns {missing}; expected columns {list(GSV_COLUMNS)}"
                )
            for line, row in enumerate(reader, start=2):
                try:
                    name = gsv_image_name(row)
                except (TypeError, ValueError) as err:
                    raise DatasetError(f"{csv_path}:{line}: malformed row ({err})") from err
                path = None
                for folder in (root / "Images" / row["city_id"], root / "Images" / csv_path.stem):
                    if folder not in listings:
                        listings[folder] = set(os.listdir(folder)) if folder.is_dir() else set()
                    if name in listings[folder]:
                        path = folder / name
                        break
                if path is None:
                    skipped += 1
                    continue
                groups[row["place_id"]].append(path)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise DatasetError(
            f"cannot read GSV-Cities dataframe {csv_path}: {_csv_problem(err)}"
        ) from err
    return list(groups.values()), skipped


def _csv_problem(err: Exception) -> str:
    """What is wrong with a CSV file, for a DatasetError."""
    if isinstance(err, UnicodeDecodeError):
        bad = err.object[err.start : err.start + 1]
        return f"it is not UTF-8 text (byte {bad!r}: {err.reason}); save it as UTF-8"
    return str(err)


def load_gsv_cities(
    root: str | Path, cities: Sequence[str] | None = None, min_images: int = 4
) -> PlaceCollection:
    """GSV-Cities places (all cities in ``Dataframes/`` unless ``cities`` names some)."""
    root = Path(root)
    frames = require_dir(root / "Dataframes", GSV_LAYOUT)
    require_dir(root / "Images", GSV_LAYOUT)
    if cities:
        csvs = [frames / f"{c}.csv" for c in cities]
        for path in csvs:
            if not path.is_file():
                raise DatasetError(f"GSV-Cities dataframe {path} not found; layout: {GSV_LAYOUT}")
    else:
        csvs = sorted(frames.glob("*.csv"))
        if not csvs:
            raise DatasetError(f"no <City>.csv in {frames}; expected layout: {GSV_LAYOUT}")
    groups: list[list[Path]] = []
    skipped = 0
    for path in csvs:
        city_groups, city_skipped = _read_gsv_city(root, path)
        groups += city_groups
        skipped += city_skipped
    return _finish(f"gsv:{root.name}", groups, min_images, GSV_LAYOUT, root, skipped)


def _gldv2_rows(root: Path) -> Iterable[tuple[str, str]]:
    """(landmark_id, image id) pairs from train_clean.csv or train.csv."""
    clean, plain = root / "train_clean.csv", root / "train.csv"
    path = clean if clean.is_file() else plain
    if not path.is_file():
        raise DatasetError(f"no {plain} or {clean}; expected layout: {GLDV2_LAYOUT}")
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        fields = reader.fieldnames or []
        if path == clean and {"landmark_id", "images"} <= set(fields):
            for row in reader:
                for image_id in row["images"].split():
                    yield row["landmark_id"], image_id
        elif path == plain and {"id", "landmark_id"} <= set(fields):
            for row in reader:
                yield row["landmark_id"], row["id"]
        else:
            raise DatasetError(f"{path} has columns {fields}; expected layout: {GLDV2_LAYOUT}")


def load_gldv2(root: str | Path, min_images: int = 2) -> PlaceCollection:
    """Google Landmarks v2 train split, one place per landmark; missing files are skipped."""
    root = require_dir(Path(root), GLDV2_LAYOUT)
    images = require_dir(root / "train", GLDV2_LAYOUT)
    groups: dict[str, list[Path]] = defaultdict(list)
    skipped = 0
    try:
        for landmark, image_id in _gldv2_rows(root):
            path = images / image_id[:1] / image_id[1:2] / image_id[2:3] / f"{image_id}.jpg"
            if len(image_id) < 3 or not path.is_file():
                skipped += 1
                continue
            groups[landmark].append(path)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise DatasetError(
            f"cannot read Google Landmarks v2 lists in {root}: {_csv_problem(err)}"
        ) from err
    return _finish(f"gldv2:{root.name}", groups.values(), min_images, GLDV2_LAYOUT, root, skipped)


def load_sfxl(
    root: str | Path, cell_m: float = 10.0, heading_deg: float = 30.0, min_images: int = 2
) -> PlaceCollection:
    """SF-XL images grouped into UTM cells x heading sectors (``heading_deg=0``: no sectors)."""
    root = require_dir(Path(root), SFXL_LAYOUT)
    groups: dict[tuple[int, int, int], list[Path]] = defaultdict(list)
    skipped = 0
    for path in list_images(root, recursive=True):
        utm = parse_utm_name(path.name)
        if utm is None:
            skipped += 1
            continue
        sector = 0
        if heading_deg > 0:
            fields = path.name.split("@")
            try:
                sector = int((float(fields[9]) % 360.0) // heading_deg)
            except (IndexError, ValueError):
                skipped += 1
                continue
        groups[(math.floor(utm[0] / cell_m), math.floor(utm[1] / cell_m), sector)].append(path)
    ordered = [groups[k] for k in sorted(groups)]
    return _finish(f"sfxl:{root.name}", ordered, min_images, SFXL_LAYOUT, root, skipped)


PLACE_LOADERS = {
    "gsv": load_gsv_cities,
    "folders": load_place_folders,
    "gldv2": load_gldv2,
    "sfxl": load_sfxl,
}


def load_places(spec: str) -> PlaceCollection:
    """Load ``KIND:ROOT`` (kind in gsv, folders, gldv2, sfxl); a bare ROOT means ``folders``."""
    kind, sep, root = spec.partition(":")
    if sep and kind in PLACE_LOADERS:
        return PLACE_LOADERS[kind](root)
    if sep and kind.isidentifier():
        raise DatasetError(f"unknown dataset kind {kind!r} in {spec!r}; use {list(PLACE_LOADERS)}")
    return load_place_folders(spec)
