"""Keyframe metadata (`KeyframeMeta`: stamp, frame, optional pose, source, robot, session), the
checks of what callers pass a PlaceMap (metadata, descriptors, dense tokens, ids: bad input
gives a MapError, never a crash), and `MetadataStore`, the metadata table of formats 1 and 2.

Maps of format version 1 have no robot / session columns: loading one adds them to the working
copy, filled with the identity the loader names (`from_saved(..., legacy=...)`). Features
(opaque bytes packed by `geometry.features.pack_features`) live in a second table, one row per
keyframe that has them, with a CRC32 checked on every read. Loading never changes the saved
files: the saved database is copied into the working folder (legacy.py converts it).
"""

from __future__ import annotations

import math
import sqlite3
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

import numpy as np

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.identity import name_problem
from pair_vpr_ros.types import Pose

_SCHEMA = """
CREATE TABLE IF NOT EXISTS keyframes (
    id INTEGER PRIMARY KEY, stamp REAL NOT NULL, frame_id TEXT NOT NULL, source TEXT NOT NULL,
    x REAL, y REAL, z REAL, qx REAL, qy REAL, qz REAL, qw REAL,
    robot TEXT NOT NULL DEFAULT '', session TEXT NOT NULL DEFAULT ''
)"""
_FEATURES_SCHEMA = """
CREATE TABLE IF NOT EXISTS features (id INTEGER PRIMARY KEY, crc INTEGER NOT NULL, data BLOB)"""
_COLUMNS_V1 = "id, stamp, frame_id, source, x, y, z, qx, qy, qz, qw"  # format version 1
_COLUMNS = _COLUMNS_V1 + ", robot, session"
# Feature rows that belong to no keyframe or are not (integer crc, blob data).
_CHECK_FEATURES = """SELECT COUNT(*) FROM features WHERE id < 0 OR id >= ?
    OR typeof(id) != 'integer' OR typeof(crc) != 'integer' OR typeof(data) != 'blob'"""
_NUMBER = "IN ('real', 'integer')"
# Row count, id range and rows whose values a KeyframeMeta cannot hold (SQLite does not enforce
# column types); fails on a table without these columns.
_CHECK = f"""SELECT COUNT(*), MIN(id), MAX(id), SUM(
    typeof(id) != 'integer' OR typeof(stamp) NOT {_NUMBER} OR typeof(frame_id) != 'text'
    OR typeof(source) != 'text' OR typeof(robot) != 'text' OR typeof(session) != 'text' OR NOT (
        (x IS NULL AND y IS NULL AND z IS NULL AND qx IS NULL AND qy IS NULL AND qz IS NULL
         AND qw IS NULL) OR (typeof(x) {_NUMBER} AND typeof(y) {_NUMBER} AND typeof(z) {_NUMBER}
         AND typeof(qx) {_NUMBER} AND typeof(qy) {_NUMBER} AND typeof(qz) {_NUMBER}
         AND typeof(qw) {_NUMBER}))
) FROM keyframes"""


@dataclass(frozen=True)
class KeyframeMeta:
    """One keyframe's metadata; `id` is assigned by `PlaceMap.add` (leave it at -1).

    stamp: seconds (e.g. header stamp sec + nanosec * 1e-9); frame_id: the image's frame.
    pose: (x, y, z, qx, qy, qz, qw) in the odometry frame, or None when unknown.
    source: free text (bag name, topic).
    robot, session: who recorded it (identity.py; "" = unnamed, e.g. a library user's map).
    """

    id: int = -1
    stamp: float = 0.0
    frame_id: str = ""
    pose: Pose | None = None
    source: str = ""
    robot: str = ""
    session: str = ""


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
    problem = identity_problem(str(meta.robot), str(meta.session))
    if problem:
        raise MapError(f"keyframe metadata: {problem}")
    return KeyframeMeta(
        meta.id, stamp, str(meta.frame_id), pose, str(meta.source), str(meta.robot),
        str(meta.session),
    )  # fmt: skip


def identity_problem(robot: str, session: str) -> str | None:
    """Why a keyframe's robot or session breaks the identity rule (identity.py); None when each
    is valid or empty ("" = unnamed, e.g. a library user's map)."""
    for kind, value in (("robot", robot), ("session", session)):
        if value and (problem := name_problem(kind, value)):
            return problem
    return None


class MetadataStore:
    """Keyframe rows in a working SQLite file `path` (created empty when missing)."""

    def __init__(self, path: Path, create: bool = True) -> None:
        self.path = Path(path)
        # Callers serialise access (LoopClosurePipeline holds a lock), so the map may be used
        # from the thread that did not open it (the node's worker and service threads).
        self._conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        # A working copy: crash durability is the saved map's job, so skip journaling costs.
        self._conn.execute("PRAGMA journal_mode=OFF")
        self._conn.execute("PRAGMA synchronous=OFF")
        if create:  # a version-1 copy is upgraded first (its table exists without identity)
            self._conn.execute(_SCHEMA)
        self._conn.execute(_FEATURES_SCHEMA)

    def _upgrade(self, saved: Path, legacy: tuple[str, str]) -> None:
        """Add robot / session columns to a copied version-1 table, named `legacy`."""
        self._check_columns(saved, _COLUMNS_V1)
        robot, session = (str(v) for v in legacy)
        for name in ("robot", "session"):
            self._conn.execute(f"ALTER TABLE keyframes ADD COLUMN {name} TEXT NOT NULL DEFAULT ''")
        self._conn.execute("UPDATE keyframes SET robot = ?, session = ?", (robot, session))

    def _check_columns(self, saved: Path, expected: str, bad: int | None = None) -> None:
        columns = [r[1] for r in self._conn.execute("PRAGMA table_info(keyframes)")]
        if columns != expected.split(", ") or bad:
            what = f"columns {columns}" if not bad else f"{bad} rows hold values of wrong type"
            raise MapError(
                f"keyframe metadata {saved} is not a place map's keyframe table ({what}; "
                f"expected columns {expected}): the map is damaged or was written by another "
                "program: restore it from a backup or rebuild it"
            )

    @classmethod
    def from_saved(
        cls, saved: Path, work: Path, count: int, legacy: tuple[str, str] | None = None
    ) -> MetadataStore:
        """Copy the saved database `saved` to `work`; it must hold exactly ids 0..count-1.
        legacy: the (robot, session) of a version-1 table (without those columns); None: the
        table must be of version 2."""
        store = None
        try:
            src = sqlite3.connect(f"file:{quote(str(saved))}?mode=ro&immutable=1", uri=True)
            try:
                dst = sqlite3.connect(work)
                src.backup(dst)
                dst.close()
            finally:
                src.close()
            store = cls(work, create=legacy is None)
            if legacy is not None:
                store._upgrade(saved, legacy)
            store._check_saved(saved, count)
        except BaseException as err:
            if store is not None:
                store.close()
            if isinstance(err, sqlite3.Error):
                raise MapError(
                    f"keyframe metadata {saved} is not a readable SQLite database ({err}); the "
                    "map is damaged: restore it from a backup or rebuild it"
                ) from err
            raise
        return store

    def _check_saved(self, saved: Path, count: int) -> None:
        """The copied table has our columns, value types and exactly ids 0..count-1."""
        self._check_columns(saved, _COLUMNS)
        n, lo, hi, bad = self._conn.execute(_CHECK).fetchone()
        self._check_columns(saved, _COLUMNS, bad)
        if (n, lo, hi) != (count, 0 if count else None, count - 1 if count else None):
            raise MapError(
                f"keyframe metadata {saved} holds {n} rows (ids {lo}..{hi}), the manifest lists "
                f"{count} keyframes: the map is damaged, restore it from a backup or rebuild it"
            )
        stray = self._conn.execute(_CHECK_FEATURES, (count,)).fetchone()[0]
        if stray:
            raise MapError(
                f"keyframe metadata {saved} holds {stray} feature rows of no keyframe or of the "
                "wrong type: the map is damaged, restore it from a backup or rebuild it"
            )

    def add(self, meta: KeyframeMeta, features: bytes = b"") -> None:
        """meta: validated, with its id set; features: packed features ("" = none)."""
        pose = meta.pose if meta.pose is not None else (None,) * 7
        self._conn.execute(
            f"INSERT INTO keyframes ({_COLUMNS}) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?)",
            (meta.id, meta.stamp, meta.frame_id, meta.source, *pose, meta.robot, meta.session),
        )
        if features:
            self._conn.execute(
                "INSERT INTO features (id, crc, data) VALUES (?, ?, ?)",
                (meta.id, zlib.crc32(features), sqlite3.Binary(features)),
            )

    def features(self, kf_id: int) -> bytes:
        """The packed features of keyframe `kf_id` (b"" when it has none); MapError when the
        stored bytes fail their CRC32."""
        row = self._conn.execute(
            "SELECT crc, data FROM features WHERE id = ?", (int(kf_id),)
        ).fetchone()
        if row is None:
            return b""
        data = bytes(row[1])
        if zlib.crc32(data) != row[0]:
            raise MapError(
                f"the features of keyframe {kf_id} fail their CRC32 check: the map is damaged; "
                "restore it from a backup or rebuild it"
            )
        return data

    def feature_stats(self) -> tuple[int, int]:
        """(keyframes with features, total bytes of their features)."""
        n, size = self._conn.execute("SELECT COUNT(*), SUM(LENGTH(data)) FROM features").fetchone()
        return int(n), int(size or 0)

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
        self._conn.execute("DELETE FROM features WHERE id >= ?", (int(kf_id),))

    def clear(self) -> None:
        self._conn.execute("DELETE FROM keyframes")
        self._conn.execute("DELETE FROM features")

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
    kf_id, stamp, frame_id, source, *pose, robot, session = row
    pose_or_none = None if pose[0] is None else tuple(pose)
    return KeyframeMeta(kf_id, stamp, frame_id, pose_or_none, source, robot, session)


# ---- validation of what callers pass to a PlaceMap: bad input gives a MapError, never a crash


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
            tokens = np.ascontiguousarray(np.asarray(dense), dtype=np.float16)
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
