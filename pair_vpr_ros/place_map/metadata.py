"""Keyframe metadata (stamp, frame, optional pose, source) in SQLite.

The live map writes to a private working database (no fsync: durability comes from `save`, which
copies it with SQLite's backup API); a saved database is opened read-only and copied in on load.
"""

from __future__ import annotations

import math
import sqlite3
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

from ..errors import MapError

Pose = tuple[float, float, float, float, float, float, float]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS keyframes (
    id INTEGER PRIMARY KEY, stamp REAL NOT NULL, frame_id TEXT NOT NULL, source TEXT NOT NULL,
    x REAL, y REAL, z REAL, qx REAL, qy REAL, qz REAL, qw REAL
)"""
_COLUMNS = "id, stamp, frame_id, source, x, y, z, qx, qy, qz, qw"


@dataclass(frozen=True)
class KeyframeMeta:
    """One keyframe's metadata; `id` is assigned by `PlaceMap.add` (leave it at -1).

    stamp: seconds (e.g. header stamp sec + nanosec * 1e-9); frame_id: the image's frame.
    pose: (x, y, z, qx, qy, qz, qw) in the odometry frame, or None when unknown.
    source: free text (bag name, session) to tell mapping sessions apart.
    """

    id: int = -1
    stamp: float = 0.0
    frame_id: str = ""
    pose: Pose | None = None
    source: str = ""


def validate_meta(meta: KeyframeMeta) -> KeyframeMeta:
    """-> a copy with plain Python types; MapError on a bad stamp or pose."""
    if not isinstance(meta, KeyframeMeta):
        raise MapError(f"keyframe metadata must be a KeyframeMeta, got {type(meta).__name__}")
    try:
        stamp = float(meta.stamp)
        pose = None if meta.pose is None else tuple(float(v) for v in meta.pose)
    except (TypeError, ValueError) as err:
        raise MapError(f"keyframe metadata has a non-numeric stamp or pose: {meta}") from err
    if not math.isfinite(stamp):
        raise MapError(f"keyframe stamp must be a finite number of seconds, got {meta.stamp}")
    if pose is not None and (len(pose) != 7 or not all(math.isfinite(v) for v in pose)):
        raise MapError(
            f"keyframe pose must be 7 finite numbers (x, y, z, qx, qy, qz, qw) or None, got {pose}"
        )
    return KeyframeMeta(meta.id, stamp, str(meta.frame_id), pose, str(meta.source))


class MetadataStore:
    """Keyframe rows in a working SQLite file `path` (created empty when missing)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        # Callers serialise access (LoopClosurePipeline holds a lock), so the map may be used
        # from the thread that did not open it (the node's worker and service threads).
        self._conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        # A working copy: crash durability is the saved map's job, so skip journaling costs.
        self._conn.execute("PRAGMA journal_mode=OFF")
        self._conn.execute("PRAGMA synchronous=OFF")
        self._conn.execute(_SCHEMA)

    @classmethod
    def from_saved(cls, saved: Path, work: Path, count: int) -> MetadataStore:
        """Copy the saved database `saved` to `work`; it must hold exactly ids 0..count-1."""
        try:
            src = sqlite3.connect(f"file:{quote(str(saved))}?mode=ro&immutable=1", uri=True)
            try:
                dst = sqlite3.connect(work)
                src.backup(dst)
                dst.close()
            finally:
                src.close()
            store = cls(work)
            n, lo, hi = store._conn.execute(
                "SELECT COUNT(*), MIN(id), MAX(id) FROM keyframes"
            ).fetchone()
        except sqlite3.DatabaseError as err:
            raise MapError(
                f"keyframe metadata {saved} is not a readable SQLite database ({err}); the map "
                "is damaged: restore it from a backup or rebuild it"
            ) from err
        if (n, lo, hi) != (count, 0 if count else None, count - 1 if count else None):
            store.close()
            raise MapError(
                f"keyframe metadata {saved} holds {n} rows (ids {lo}..{hi}), the manifest lists "
                f"{count} keyframes: the map is damaged, restore it from a backup or rebuild it"
            )
        return store

    def add(self, meta: KeyframeMeta) -> None:
        """meta: validated, with its id set."""
        pose = meta.pose if meta.pose is not None else (None,) * 7
        self._conn.execute(
            f"INSERT INTO keyframes ({_COLUMNS}) VALUES (?,?,?,?,?,?,?,?,?,?,?)",
            (meta.id, meta.stamp, meta.frame_id, meta.source, *pose),
        )

    def get(self, kf_id: int) -> KeyframeMeta | None:
        row = self._conn.execute(
            f"SELECT {_COLUMNS} FROM keyframes WHERE id = ?", (int(kf_id),)
        ).fetchone()
        return None if row is None else _from_row(row)

    def all(self) -> list[KeyframeMeta]:
        rows = self._conn.execute(f"SELECT {_COLUMNS} FROM keyframes ORDER BY id")
        return [_from_row(r) for r in rows]

    def delete_from(self, kf_id: int) -> None:
        """Remove rows with id >= kf_id (undo of a failed add)."""
        self._conn.execute("DELETE FROM keyframes WHERE id >= ?", (int(kf_id),))

    def clear(self) -> None:
        self._conn.execute("DELETE FROM keyframes")

    def save_to(self, path: Path) -> None:
        """Write a consistent copy of the database to a new file `path`."""
        dst = sqlite3.connect(path)
        try:
            self._conn.backup(dst)
        finally:
            dst.close()

    def close(self) -> None:
        self._conn.close()


def _from_row(row: tuple) -> KeyframeMeta:
    kf_id, stamp, frame_id, source, *pose = row
    return KeyframeMeta(kf_id, stamp, frame_id, None if pose[0] is None else tuple(pose), source)
