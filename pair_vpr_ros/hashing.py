"""File digests: which weights a model runs (`model.checkpoint`) and whether a saved map's small
files are intact (`place_map.manifest`)."""

from __future__ import annotations

import hashlib
import os


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes, read in blocks (checkpoints are gigabytes)."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()
