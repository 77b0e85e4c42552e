"""Read-your-own-writes without waiting for Milvus' time tick (milvus_consistency "Bounded").

A Milvus server makes an insert visible to searches at its next time tick (200 ms by default):
a Strong search waits for it (~200 ms per search measured, docs/milvus.md), a Bounded search
does not wait but may miss rows written in the last `common.gracefulTime` (5 s by default).
The map keeps its own copy of every descriptor anyway (index.py), so the rows it wrote in
the last FRESH_S seconds are searched here, exactly, under the same eligibility rules as the
server's filter, and merged with the server's answer: every keyframe the map inserted is
found by its next search, and no search waits for a tick.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np

from pair_vpr_ros.place_map.milvus.expr import Exclusion

# Milvus' default common.gracefulTime is 5 s: a Bounded search sees every row written before
# (its start - 5 s). Twice that, so a slow round trip or a clock step cannot open a gap.
FRESH_S = 10.0
Row = tuple[str, str, float]  # robot, session, stamp


class FreshRows:
    """When the map's rows were acknowledged by Milvus, to know which may not be visible yet."""

    def __init__(self, window_s: float = FRESH_S) -> None:
        self.window_s = float(window_s)
        self._marks: deque[tuple[int, float]] = deque()  # (first row of a write, time)

    def written(self, lo: int) -> None:
        """Rows from `lo` on were just acknowledged (an insert or upsert returned)."""
        self._marks.append((int(lo), time.monotonic()))

    def clear(self) -> None:
        self._marks.clear()

    def first(self, n: int) -> int:
        """The first row (of n) that a Bounded search may not see yet; n when none."""
        old = time.monotonic() - self.window_s
        while self._marks and self._marks[0][1] < old:
            self._marks.popleft()
        return min(self._marks[0][0], n) if self._marks else n


def local_mask(
    rows: list[Row], lo: int, count: int, allowed: np.ndarray | None, exclusion: Exclusion | None
) -> np.ndarray:
    """bool [max(count - lo, 0)]: which of rows [lo, count) the server's filter of the same
    arguments lets through (milvus_expr.ids_expr / exclusion_expr, evaluated here); `count` is
    the search's id limit (max_id + 1, or the map's size)."""
    ids = np.arange(lo, max(lo, count))
    if exclusion is None:
        ok = np.ones(len(ids), bool)
        if allowed is not None:
            allowed = np.asarray(allowed, bool)
            ok &= ids < len(allowed)
            ok[ok] = allowed[ids[ok]]
        return ok
    q, s = float(exclusion.stamp), float(exclusion.exclude_s)
    part = rows[lo : len(ids) + lo]
    stamps = np.array([t for _, _, t in part], np.float64)
    own = np.array([r == exclusion.robot and ss == exclusion.session for r, ss, _ in part], bool)
    far = (stamps <= q - s) | (stamps >= q + s) if s > 0 else stamps != q
    mine = (ids < min(int(exclusion.limit), count)) & far
    return (~own | mine).reshape(len(ids))


def local_search(
    desc: np.ndarray, query: np.ndarray, lo: int, mask: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """desc [n, dim] (the map's copy), query [dim]; rows lo + j with mask[j] -> (ids [<=k],
    inner products [<=k]) best first."""
    ids = lo + np.flatnonzero(mask)
    sims = desc[ids] @ np.asarray(query, np.float32).reshape(-1)
    order = np.argsort(-sims, kind="stable")[:k]
    return ids[order].astype(np.int64), sims[order].astype(np.float32)


def merge(
    a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray], k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Two (ids, sims) answers -> the best k distinct ids, best first (a row the server
    already sees is in both)."""
    ids = np.concatenate([a[0], b[0]])
    sims = np.concatenate([a[1], b[1]]).astype(np.float32)
    order = np.argsort(-sims, kind="stable")
    seen: set[int] = set()
    keep = [i for i in order if not (int(ids[i]) in seen or seen.add(int(ids[i])))][:k]
    return ids[keep].astype(np.int64), sims[keep]
