"""Evaluation sets (``load_eval_set(ROOT)``): database and query images, ground truth.

Ground truth is ``ROOT/ground_truth.npy`` (read without pickle) or UTM file names; see
:mod:`pair_vpr_ros.learn` for the rules.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pair_vpr_ros.errors import DatasetError
from pair_vpr_ros.learn.image_files import list_images, parse_utm_name, require_dir

EVAL_LAYOUT = (
    "ROOT/database/*.jpg and ROOT/queries/*.jpg (@easting@northing@ names or ground_truth.npy)"
)


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
    db_dir = require_dir(root / "database", EVAL_LAYOUT)
    q_dir = require_dir(root / "queries", EVAL_LAYOUT)
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
