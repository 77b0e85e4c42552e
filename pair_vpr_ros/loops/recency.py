"""Which map keyframes a query may match, by time, and clock jumps backwards.

A loop needs two moments far apart in time. Keyframe ids grow with insertion, stamps need not: a
bag played again (`ros2 bag play --loop`), a simulated clock reset or a map recorded on another
clock puts keyframes stamped at, near or after the query's stamp into the map. So recent
keyframes are excluded by stamp distance over the whole map (never by walking back along ids,
which assumed growing stamps and let a replayed bag match its own first pass at the same stamp),
and a stamp well before the newest one starts a new session (`ClockWatch`).

Stamps are compared only within one robot and one session (`GroupedRecency`): another robot or
session ran on another clock, so its keyframes are candidates at once whatever their stamps.
The live session's keyframes are the newest ids, so the eligible ids stay one prefix (a FAISS
`IDSelectorRange`, found by bisection); a session whose ids sit in the middle of the map excludes
one id range (`Eligible.exclude`), and only unsorted stamps or scattered ids need a mask.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

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


@dataclass(frozen=True)
class Eligible:
    """The ids a query may match, one of three forms (`count` ids in all, >= 1):
    `prefix` ids 0..prefix-1; all ids but `exclude` = (lo, hi), i.e. lo..hi-1; or `mask`
    (bool [m], ids >= m not eligible). `PlaceMap.search` takes each form."""

    count: int
    prefix: int | None = None
    exclude: tuple[int, int] | None = None
    mask: np.ndarray | None = None


class _Group:
    """The keyframes of one robot-session: ids (growing) and stamps, by insertion."""

    def __init__(self) -> None:
        self.ids: list[int] = []
        self.stamps = StampBuffer()
        self.contiguous = True  # ids[i] == ids[0] + i

    def append(self, kf_id: int, stamp: float) -> None:
        if self.ids and kf_id != self.ids[-1] + 1:
            self.contiguous = False
        self.ids.append(kf_id)
        self.stamps.append(stamp)


class GroupedRecency:
    """Keyframe stamps of a map by robot-session, for `eligible` (recent-keyframe exclusion
    within the query's own robot and session only)."""

    def __init__(self, keyframes: Iterable[tuple[int, float, str, str]] = ()) -> None:
        """keyframes: (id, stamp, robot, session), ids 0, 1, 2, ... in order."""
        self._groups: dict[tuple[str, str], _Group] = {}
        self._size = 0
        for kf_id, stamp, robot, session in keyframes:
            self.append(kf_id, stamp, robot, session)

    def __len__(self) -> int:
        return self._size

    def append(self, kf_id: int, stamp: float, robot: str, session: str) -> None:
        self._groups.setdefault((robot, session), _Group()).append(int(kf_id), float(stamp))
        self._size = max(self._size, int(kf_id) + 1)

    def own_limit(self, robot: str, session: str, exclude_n: int) -> int:
        """The first id of the newest `exclude_n` keyframes of (robot, session), i.e. its ids
        below this may match (an index filter's form of the rule; the map's size when the
        group is empty or exclude_n is 0)."""
        group = self._groups.get((robot, session))
        if group is None or not group.ids or exclude_n <= 0:
            return self._size
        return group.ids[-min(int(exclude_n), len(group.ids))]

    def sessions(self) -> dict[tuple[str, str], int]:
        """{(robot, session): keyframes}."""
        return {key: len(g.ids) for key, g in self._groups.items()}

    def eligible(
        self, stamp: float, robot: str, session: str, exclude_s: float, exclude_n: int
    ) -> Eligible | None:
        """What a query at `stamp` of (robot, session) may match: every keyframe of another
        robot or session, and those of its own that `eligible_keyframes` lets through; None
        when nothing is eligible."""
        n, group = self._size, self._groups.get((robot, session))
        if group is None or not group.ids:
            return Eligible(n, prefix=n) if n else None
        own = group.stamps.eligible(stamp, exclude_s, exclude_n)
        first, m = group.ids[0], len(group.ids)
        if isinstance(own, int) or own is None:  # own eligible: positions 0..own-1 of the group
            kept = own or 0
            if group.contiguous:
                lo, hi = first + kept, first + m
                if hi == n:  # the newest ids: a prefix (a live session)
                    return Eligible(lo, prefix=lo) if lo else None
                return Eligible(n - (hi - lo), exclude=(lo, hi))
            own = np.arange(m) < kept
        mask = np.ones(n, dtype=bool)
        ids = np.asarray(group.ids, dtype=np.int64)
        mask[ids[: len(own)][~own]] = False
        mask[ids[len(own) :]] = False
        count = int(mask.sum())
        return Eligible(count, mask=mask) if count else None


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
