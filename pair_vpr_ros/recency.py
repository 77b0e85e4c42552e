"""Which map keyframes a query may match, by time, and clock jumps backwards.

A loop needs two moments far apart in time. Keyframe ids grow with insertion, stamps need not: a
bag played again (`ros2 bag play --loop`), a simulated clock reset or a map recorded on another
clock puts keyframes stamped at, near or after the query's stamp into the map. So recent
keyframes are excluded by stamp distance over the whole map (never by walking back along ids,
which assumed growing stamps and let a replayed bag match its own first pass at the same stamp),
and a stamp well before the newest one starts a new session (`ClockWatch`).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

CLOCK_JUMP_S = 1.0  # a stamp this far before the newest one is a clock jump, not reordering


class StampBuffer:
    """Keyframe stamps by id: a growable float64 array (`values` [n], s)."""

    def __init__(self, stamps: Iterable[float] = ()) -> None:
        given = np.asarray(list(stamps), dtype=np.float64)
        self._data = np.zeros(max(1024, len(given)))
        self._data[: len(given)] = given
        self._size = len(given)
        self.sorted = bool(np.all(given[1:] >= given[:-1]))  # non-decreasing: the usual case

    def __len__(self) -> int:
        return self._size

    @property
    def values(self) -> np.ndarray:
        return self._data[: self._size]

    def append(self, stamp: float) -> None:
        if self._size == len(self._data):
            self._data = np.concatenate([self._data, np.zeros_like(self._data)])
        if self._size and stamp < self._data[self._size - 1]:
            self.sorted = False
        self._data[self._size] = stamp
        self._size += 1

    def eligible(self, stamp: float, exclude_s: float, exclude_n: int) -> int | np.ndarray | None:
        """`eligible_keyframes` of these stamps; while they are sorted, found by bisection in
        O(log n) and, when the eligible ids are a prefix (a live run: nothing stamped after the
        query), given as its length (int) instead of a mask."""
        if not self.sorted:
            return eligible_keyframes(self.values, stamp, exclude_s, exclude_n)
        stamps = self.values[: max(self._size - int(exclude_n), 0)]
        older = np.searchsorted(stamps, stamp - exclude_s, "right" if exclude_s else "left")
        newer = np.searchsorted(stamps, stamp + exclude_s, "left" if exclude_s else "right")
        if newer >= len(stamps):
            return int(older) or None
        mask = np.zeros(len(stamps), dtype=bool)
        mask[:older] = mask[newer:] = True
        return mask


def eligible_keyframes(
    stamps: np.ndarray, stamp: float, exclude_s: float, exclude_n: int
) -> np.ndarray | None:
    """Keyframes a query at `stamp` may match: bool [m], m <= len(stamps) (ids >= m are not
    eligible), or None when none is. Excluded: the newest `exclude_n` ids, every keyframe whose
    stamp lies within `exclude_s` of the query's (before or after it), and any at the very same
    stamp (even with `exclude_s` 0)."""
    limit = len(stamps) - int(exclude_n)
    if limit <= 0:
        return None
    near = stamps[:limit] - stamp
    mask = (np.abs(near) >= exclude_s) & (near != 0.0)
    return mask if mask.any() else None


class ClockWatch:
    """Tracks the newest stamp of a stream; `check` tells a jump backwards from reordering."""

    def __init__(self, tolerance_s: float = CLOCK_JUMP_S) -> None:
        self.tolerance_s = tolerance_s
        self.newest: float | None = None

    def reset(self) -> None:
        self.newest = None

    def check(self, stamp: float) -> float:
        """How far (s) `stamp` jumped back from the newest stamp (0.0: no jump; a jump makes
        `stamp` the newest: the start of a new session)."""
        newest = self.newest
        if newest is not None and stamp < newest - self.tolerance_s:
            self.newest = stamp
            return newest - stamp
        self.newest = stamp if newest is None else max(newest, stamp)
        return 0.0
