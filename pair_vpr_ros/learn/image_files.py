"""Image files of a dataset on disk: folder checks, listing, UTM file names, reading to RGB."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from pair_vpr_ros.errors import DatasetError, ImageConversionError
from pair_vpr_ros.images.encoded import IMAGE_SUFFIXES, file_to_rgb
from pair_vpr_ros.model import preprocess


def require_dir(path: Path, layout: str) -> Path:
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


def read_rgb(path: str | Path) -> np.ndarray:
    """Image file -> [H,W,3] uint8 RGB, decoded as the node decodes image files
    (`images.encoded.file_to_rgb`); DatasetError if missing, undecodable or too large."""
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
