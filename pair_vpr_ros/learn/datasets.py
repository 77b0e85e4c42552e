"""Training and evaluation datasets on disk (ROS-free, nothing is downloaded).

Place collections (training; ``load_places("KIND:ROOT")``):

- ``gsv``: GSV-Cities. ``ROOT/Dataframes/<City>.csv`` (columns place_id, year, month, northdeg,
  city_id, lat, lon, panoid) and ``ROOT/Images/<city_id>/<name>.jpg`` where, as in the dataset's
  reference loader, ``name = f"{city_id}_{place_id:07d}_{year:04d}_{month:02d}_{northdeg:03d}_"
  f"{lat}_{lon}_{panoid}"`` with lat/lon written as Python ``str(float)``. ``Images/<City>/`` (the
  CSV stem) is accepted too. Places with fewer than 4 images are dropped; rows without an image
  file are counted in ``skipped_images``.
- ``folders``: ``ROOT/<place>/*.{png,jpg,...}`` (``imaging.IMAGE_SUFFIXES``), one subfolder per
  place, >= 2 images each.
- ``gldv2``: Google Landmarks v2. ``ROOT/train_clean.csv`` (landmark_id, images: space-separated
  ids) if present, else ``ROOT/train.csv`` (id, url, landmark_id); image ``id`` lives at
  ``ROOT/train/<id[0]>/<id[1]>/<id[2]>/<id>.jpg``. One landmark is one place.
- ``sfxl``: SF-XL. Images anywhere under ROOT named ``@east@north@zone@letter@lat@lon@pano@tile@
  heading@...``; a place is a square UTM cell (default 10 m) times a heading sector (default 30
  degrees), like CosPlace's cells but without its group separation.

Evaluation sets (``load_eval_set(ROOT)``): ``ROOT/database/`` and ``ROOT/queries/`` image folders
(searched recursively, sorted by relative path). Ground truth is ``ROOT/ground_truth.npy`` when
present, otherwise UTM coordinates in the file names (``@easting@northing@...``) with positives
within 25 m. The .npy is read without pickle (a pickle can run code): an integer array
``[Q, K]`` of positive database indices per query padded with -1, or a boolean ``[Q, DB]``
matrix. The ragged object arrays other VPR code writes are refused with the one-line conversion
(``GT_CONVERT``) to run once on a file you trust.
"""

from __future__ import annotations

import csv
import math
import os
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from pair_vpr_ros.encoded_image import IMAGE_SUFFIXES, file_to_rgb
from pair_vpr_ros.errors import DatasetError, ImageConversionError
from pair_vpr_ros.model import preprocess

GSV_COLUMNS = ("place_id", "year", "month", "northdeg", "city_id", "lat", "lon", "panoid")
GSV_LAYOUT = "ROOT/Dataframes/<City>.csv and ROOT/Images/<city_id>/<city_id>_<place_id:07d>_...jpg"
FOLDERS_LAYOUT = "ROOT/<place_name>/*.{png,jpg,jpeg,bmp,tif,tiff,webp} (one subfolder per place)"
GLDV2_LAYOUT = (
    "ROOT/train.csv (id,url,landmark_id) or ROOT/train_clean.csv + ROOT/train/a/b/c/abc...jpg"
)
SFXL_LAYOUT = "images named @easting@northing@zone@letter@lat@lon@pano@tile@heading@... under ROOT"
EVAL_LAYOUT = (
    "ROOT/database/*.jpg and ROOT/queries/*.jpg (@easting@northing@ names or ground_truth.npy)"
)


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


def _require_dir(path: Path, layout: str) -> Path:
    if not path.is_dir():
        raise DatasetError(f"dataset folder {path} does not exist; expected layout: {layout}")
    return path


def _is_image(name: str) -> bool:
    return name.lower().endswith(IMAGE_SUFFIXES)


def list_images(folder: Path, recursive: bool = False) -> list[Path]:
    """Image files (``IMAGE_SUFFIXES``, any case) in ``folder``, sorted by relative path."""
    if not recursive:
        return sorted(p for p in folder.iterdir() if p.is_file() and _is_image(p.name))
    found = [Path(d) / f for d, _, files in os.walk(folder) for f in files if _is_image(f)]
    return sorted(found, key=lambda p: p.relative_to(folder).as_posix())


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
    root = _require_dir(Path(root), FOLDERS_LAYOUT)
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
    frames = _require_dir(root / "Dataframes", GSV_LAYOUT)
    _require_dir(root / "Images", GSV_LAYOUT)
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
    root = _require_dir(Path(root), GLDV2_LAYOUT)
    images = _require_dir(root / "train", GLDV2_LAYOUT)
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


def parse_utm_name(name: str) -> tuple[float, float] | None:
    """(easting, northing) from ``@easting@northing@...`` file names, None if absent."""
    parts = name.split("@")
    if len(parts) < 4:
        return None
    try:
        east, north = float(parts[1]), float(parts[2])
    except ValueError:
        return None
    return (east, north) if math.isfinite(east) and math.isfinite(north) else None


def load_sfxl(
    root: str | Path, cell_m: float = 10.0, heading_deg: float = 30.0, min_images: int = 2
) -> PlaceCollection:
    """SF-XL images grouped into UTM cells x heading sectors (``heading_deg=0``: no sectors)."""
    root = _require_dir(Path(root), SFXL_LAYOUT)
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


@dataclass(frozen=True)
class EvalSet:
    """A retrieval benchmark: ``positives[q]`` are the database indices matching query ``q``."""

    name: str
    database: tuple[Path, ...]
    queries: tuple[Path, ...]
    positives: tuple[np.ndarray, ...]


def positives_within(db_xy: np.ndarray, q_xy: np.ndarray, radius: float) -> list[np.ndarray]:
    """For each query [Q,2] the sorted int64 indices of database points [M,2] within ``radius``."""
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        out = []
        for start in range(0, len(q_xy), 1024):
            d2 = ((q_xy[start : start + 1024, None, :] - db_xy[None]) ** 2).sum(-1)
            out += [np.flatnonzero(row <= radius * radius).astype(np.int64) for row in d2]
        return out
    hits = cKDTree(db_xy).query_ball_point(q_xy, r=radius)
    return [np.sort(np.asarray(h, dtype=np.int64)) for h in hits]


def _utm_of(paths: Sequence[Path], folder: Path) -> np.ndarray:
    coords = []
    for path in paths:
        utm = parse_utm_name(path.name)
        if utm is None:
            raise DatasetError(
                f"{path} has no @easting@northing@ in its name and "
                f"{folder.parent}/ground_truth.npy is missing; expected layout: {EVAL_LAYOUT}"
            )
        coords.append(utm)
    return np.asarray(coords, dtype=np.float64).reshape(-1, 2)


GT_CONVERT = (
    "python -c \"import numpy as np; g = np.load('ground_truth.npy', allow_pickle=True); "
    "k = max(map(len, g), default=0); np.save('ground_truth.npy', np.array([list(r) + [-1] * "
    '(k - len(r)) for r in g], dtype=np.int64).reshape(len(g), k))"'
)
_NPY_MAGIC = b"\x93NUMPY"


def _read_npy(path: Path) -> np.ndarray:
    """A .npy file's array, never unpickling anything; DatasetError for anything else."""
    try:
        with path.open("rb") as fh:
            magic = fh.read(len(_NPY_MAGIC))
        if magic != _NPY_MAGIC:
            raise DatasetError(
                f"ground truth {path} is not a NumPy .npy file (it starts with {magic!r}); "
                "save it with numpy.save"
            )
        return np.load(path, allow_pickle=False)
    except ValueError as err:
        if "allow_pickle" in str(err):  # an object array: its entries are pickled
            raise DatasetError(
                f"ground truth {path} is an object array (a ragged list of positives per query), "
                "which only loads by unpickling, and a pickle can run code: it is not loaded. If "
                f"you trust the file, convert it once in its folder: {GT_CONVERT}"
            ) from err
        raise DatasetError(f"cannot read ground truth {path}: {err}") from err
    except (OSError, EOFError) as err:
        raise DatasetError(f"cannot read ground truth {path}: {err}") from err


def _load_ground_truth(path: Path, num_queries: int, num_db: int) -> list[np.ndarray]:
    """-> the sorted positive database indices [P_q] int64 of each query."""
    raw = _read_npy(path)
    layout = "an integer [queries, K] array padded with -1, or a boolean [queries, database]"
    if raw.ndim == 0 or len(raw) != num_queries:
        count = "a scalar" if raw.ndim == 0 else f"{len(raw)} entries"
        raise DatasetError(f"{path} has {count} but there are {num_queries} queries")
    if raw.dtype == bool and raw.ndim == 2 and raw.shape[1] == num_db:
        return [np.flatnonzero(row).astype(np.int64) for row in raw]
    if not np.issubdtype(raw.dtype, np.integer) or raw.ndim > 2:
        raise DatasetError(
            f"{path} holds a {raw.dtype} array of shape {list(raw.shape)}; expected {layout} "
            f"(database: {num_db} images)"
        )
    out = []
    for q, row in enumerate(raw.reshape(num_queries, -1).astype(np.int64)):
        idx = row[row != -1]  # -1 pads rows to one length
        if idx.size and (idx.min() < 0 or idx.max() >= num_db):
            raise DatasetError(f"{path}: query {q} names database index outside 0..{num_db - 1}")
        out.append(np.sort(idx))
    return out


def load_eval_set(
    root: str | Path, radius_m: float = 25.0, ground_truth: str | Path | None = None
) -> EvalSet:
    """``ROOT/database`` + ``ROOT/queries`` with .npy or UTM ground truth (module docstring)."""
    root = Path(root)
    db_dir = _require_dir(root / "database", EVAL_LAYOUT)
    q_dir = _require_dir(root / "queries", EVAL_LAYOUT)
    database, queries = list_images(db_dir, True), list_images(q_dir, True)
    for folder, found in ((db_dir, database), (q_dir, queries)):
        if not found:
            raise DatasetError(f"no images in {folder}; expected layout: {EVAL_LAYOUT}")
    gt_path = Path(ground_truth) if ground_truth else root / "ground_truth.npy"
    if ground_truth and not gt_path.is_file():
        raise DatasetError(f"ground truth file {gt_path} not found")
    if gt_path.is_file():
        positives = _load_ground_truth(gt_path, len(queries), len(database))
    else:
        positives = positives_within(_utm_of(database, db_dir), _utm_of(queries, q_dir), radius_m)
    return EvalSet(root.name, tuple(database), tuple(queries), tuple(positives))


def read_rgb(path: str | Path) -> np.ndarray:
    """Image file -> [H,W,3] uint8 RGB, decoded as the node decodes image files
    (`imaging.file_to_rgb`); DatasetError if missing, undecodable or too large."""
    try:
        return file_to_rgb(path)
    except ImageConversionError as err:
        raise DatasetError(str(err)) from err


class ImageFiles(Dataset):
    """Plain image list for feature extraction: item ``i`` -> (image [3,S,S] float32, i)."""

    def __init__(self, paths: Sequence[Path], size: int) -> None:
        self.paths = list(paths)
        self.size = size

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, int]:
        return preprocess(read_rgb(self.paths[index]), size=self.size), index
