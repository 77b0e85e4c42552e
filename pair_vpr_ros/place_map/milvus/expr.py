"""Milvus scalar filter expressions of the place map's eligibility rules.

Milvus ranks only the rows a filter lets through, so the top-K are never eaten by recent frames
and nothing is fetched to be thrown away. Rows of one map are keyed `pk = (writer << 32) | id`
(see index.py): "ids < n of this map" is one primary-key range.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pair_vpr_ros.identity import DEFAULT_ROBOT, session_from_time

ID_BITS = 32  # keyframe ids of one map: 0 .. 2^32 - 1
MAX_WRITER = 2**31 - 1  # writer keys: 1 .. MAX_WRITER, so pk stays a positive int64


def utc_session() -> str:
    """Issue 22's default session id: the start time, UTC, YYYYMMDDTHHMMSSZ."""
    return session_from_time()


def identity(item: Any, session: str) -> tuple[str, str]:
    """(robot, session) of a keyframe or frame: its own `robot` / `session` when it has them
    (issue 22), else DEFAULT_ROBOT and `session` (the map's start time)."""
    robot = str(getattr(item, "robot", "") or DEFAULT_ROBOT)
    return robot, str(getattr(item, "session", "") or session)


@dataclass(frozen=True)
class Exclusion:
    """Which keyframes a query may match (the pipeline's temporal rules, issue 22's identity).

    A keyframe of the query's own robot and session is a candidate when its id is below
    `limit` (the newest `exclude_recent_keyframes` left out) and its stamp lies at least
    `exclude_s` from the query's `stamp` (never at the very same stamp). A keyframe of another
    robot or session is a candidate at once.
    """

    stamp: float
    exclude_s: float
    limit: int
    robot: str
    session: str


def quote(text: str) -> str:
    """A Milvus string literal (JSON escaping: quotes and backslashes cannot end it early)."""
    return json.dumps(str(text))


def id_range(base: int, lo: int, hi: int) -> str:
    """Rows of this map with ids in [lo, hi)."""
    return f"(pk >= {base + int(lo)} and pk < {base + int(hi)})"


def mask_runs(allowed: np.ndarray) -> list[tuple[int, int]]:
    """bool [m] -> the runs [lo, hi) of True values, in order."""
    edges = np.diff(np.concatenate([[0], allowed.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]


def ids_expr(base: int, limit: int, allowed: np.ndarray | None) -> str | None:
    """Ids < limit that `allowed` (bool [m], or None for all) lets through, as a filter; None
    when no id is eligible. A temporal mask is at most a few runs, so the filter stays short."""
    if allowed is None:
        return id_range(base, 0, limit) if limit > 0 else None
    runs = mask_runs(np.asarray(allowed, dtype=bool)[: max(limit, 0)])
    if not runs:
        return None
    return "(" + " or ".join(id_range(base, lo, hi) for lo, hi in runs) + ")"


def exclusion_expr(
    base: int, count: int, ex: Exclusion, own_runs: list | None = None
) -> str | None:
    """The filter of `ex` over ids < count of the map keyed `base`; None when nothing is
    eligible for certain (an empty map). own_runs: the id runs [lo, hi) of the map's rows of
    `ex`'s robot and session (`IdentityRuns`), so the filter compares numbers only; None: it
    compares the robot and session fields (Milvus 2.3 does that row by row: at 1e6 rows
    ~8 ms of a filtered search's ~23 ms, docs/milvus.md)."""
    if count <= 0:
        return None
    q, s = float(ex.stamp), float(ex.exclude_s)
    if not (math.isfinite(q) and math.isfinite(s)):
        raise ValueError(f"exclusion stamp and window must be finite, got {q}, {s}")
    far = f"(stamp <= {q - s!r} or stamp >= {q + s!r})" if s > 0 else f"stamp != {q!r}"
    own = f"(robot == {quote(ex.robot)} and session == {quote(ex.session)})"
    if own_runs is not None and len(own_runs) <= MAX_RUNS:
        if not own_runs:  # none of this map's rows is the query's robot-session
            return id_range(base, 0, count)
        own = "(" + " or ".join(id_range(base, lo, hi) for lo, hi in own_runs) + ")"
    limit = min(int(ex.limit), count)
    mine = f"(pk < {base + max(limit, 0)} and {far})"  # limit 0: pk < base, none of them
    return f"{id_range(base, 0, count)} and (not {own} or {mine})"


MAX_RUNS = 8  # an identity in more runs than this is filtered by its fields instead


class IdentityRuns:
    """Where each (robot, session) lies among a map's rows: id runs [lo, hi), brought up to
    date from the rows list as it grows (a map's rows of one session are one run, unless
    maps were merged)."""

    def __init__(self) -> None:
        self._runs: dict[tuple[str, str], list[list[int]]] = {}
        self._seen, self._list, self._last = 0, None, None

    def of(self, rows: list, robot: str, session: str) -> list[tuple[int, int]]:
        """rows: the map's (robot, session, stamp) each -> the runs of (robot, session)."""
        replaced = rows is not self._list or len(rows) < self._seen
        if replaced or (self._seen and rows[self._seen - 1] != self._last):
            self._runs, self._seen, self._list = {}, 0, rows
        for i in range(self._seen, len(rows)):
            runs = self._runs.setdefault((rows[i][0], rows[i][1]), [])
            if runs and runs[-1][1] == i:
                runs[-1][1] = i + 1
            else:
                runs.append([i, i + 1])
        self._seen = len(rows)
        self._last = rows[-1] if rows else None
        return [(lo, hi) for lo, hi in self._runs.get((robot, session), [])]
