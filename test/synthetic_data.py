"""Tiny synthetic place datasets for the dataset, evaluation and training tests."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np


def place_image(place: int, view: int, size: int = 64) -> np.ndarray:
    """[size,size,3] uint8: a coarse colour layout fixed per place, shifted and noised per view."""
    layout = np.random.default_rng(place).integers(0, 256, (6, 6, 3), dtype=np.uint8)
    big = cv2.resize(layout, (size + 8, size + 8), interpolation=cv2.INTER_LINEAR)
    rng = np.random.default_rng(1000 * place + view)
    dy, dx = rng.integers(0, 8, 2)
    crop = big[dy : dy + size, dx : dx + size].astype(np.int16)
    noisy = crop + rng.integers(-12, 13, crop.shape)
    return np.clip(noisy, 0, 255).astype(np.uint8)


def write_rgb(path: Path, rgb: np.ndarray) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return path


def make_place_folders(root: Path, places: int, per_place: int, size: int = 64) -> Path:
    """ROOT/place_XX/img_Y.png."""
    for p in range(places):
        for v in range(per_place):
            write_rgb(root / f"place_{p:02d}" / f"img_{v}.png", place_image(p, v, size))
    return root


def make_utm_eval_set(root: Path, places: int, size: int = 64) -> Path:
    """One database and one query image per place, 100 m apart along easting, UTM names."""
    for p in range(places):
        east, north = 500000.0 + 100.0 * p, 4000000.0
        write_rgb(
            root / "database" / f"@{east:.2f}@{north:.2f}@db{p}.jpg", place_image(p, 0, size)
        )
        write_rgb(
            root / "queries" / f"@{east + 3:.2f}@{north:.2f}@q{p}.jpg", place_image(p, 1, size)
        )
    return root
