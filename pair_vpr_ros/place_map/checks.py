"""Validation of what callers pass to a PlaceMap: bad input gives a MapError, never a crash."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map.dense_store import DTYPE


def unit_descriptor(desc: np.ndarray, dim: int) -> np.ndarray:
    """desc [dim] (or [1, dim]) -> [dim] float32 with unit L2 norm."""
    try:
        vec = np.asarray(desc, dtype=np.float32)
    except (TypeError, ValueError) as err:
        raise MapError(f"descriptor is not a numeric array: {err}") from err
    if vec.size != dim or vec.ndim > 2:
        raise MapError(f"descriptor must have shape [{dim}], got {list(vec.shape)}")
    vec = vec.reshape(dim)
    norm = float(np.linalg.norm(vec))
    if not np.isfinite(norm) or norm == 0.0:
        raise MapError(f"descriptor must be finite and non-zero (its norm is {norm})")
    return vec / np.float32(norm)


def dense_tokens(dense: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """dense [N, D] any real dtype (numpy or CPU tensor) -> [N, D] float16, C-contiguous."""
    try:
        with np.errstate(over="ignore"):  # overflow to inf is reported below, with context
            tokens = np.ascontiguousarray(np.asarray(dense), dtype=DTYPE)
    except (TypeError, ValueError) as err:
        raise MapError(f"dense tokens are not a numeric array: {err}") from err
    if tokens.shape != shape:
        raise MapError(f"dense tokens must have shape {list(shape)}, got {list(tokens.shape)}")
    if not np.isfinite(tokens).all():
        raise MapError("dense tokens contain NaN/inf (or values beyond the float16 range)")
    return tokens


def keyframe_ids(ids: Iterable[int], count: int) -> np.ndarray:
    """ids: 1-D sequence of ints in [0, count) -> [K] int64."""
    try:
        arr = np.asarray(ids if isinstance(ids, np.ndarray) else list(ids))
    except TypeError as err:
        raise MapError(f"keyframe ids must be a sequence of ints, got {ids!r}") from err
    if arr.size == 0:
        return np.empty(0, np.int64)
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise MapError(f"keyframe ids must be a 1-D sequence of ints, got {ids!r}")
    arr = arr.astype(np.int64)
    bad = arr[(arr < 0) | (arr >= count)]
    if bad.size:
        raise MapError(f"keyframe ids {bad[:5].tolist()} are not in the map (ids 0..{count - 1})")
    return arr
