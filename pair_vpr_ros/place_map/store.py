"""The keyframe store of a format-3 map: one SQLite database per map generation.

Each keyframe is one row (metadata, its [desc_dim] float32 descriptor, the CRC32 of its stored
dense entry and a CRC32 of the whole row), its packed features one row of `features` (with their
own CRC32), and `state` names the index snapshot of non-flat kinds. Every value a load or query
uses is checked against a CRC32 when read, so a flipped bit is reported, never used.

The database of a saved map is used in place (WAL mode, synchronous=FULL): the live map keeps one
write transaction open, its adds go into it, and `commit` (the save) makes them durable in one
SQLite commit. A kill -9 before the commit rolls them back: the last save stays. A map that was
never saved keeps its store in its working folder, committed row by row (no fsync).
"""

from __future__ import annotations

import sqlite3
import struct
import zlib
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import quote

import numpy as np

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map.growth.tables import GROWTH_SCHEMA, GROWTH_TABLES, GrowthTables
from pair_vpr_ros.place_map.metadata import KeyframeMeta

_SCHEMA = (
    """CREATE TABLE IF NOT EXISTS keyframes (
    id INTEGER PRIMARY KEY, stamp REAL NOT NULL, frame_id TEXT NOT NULL, source TEXT NOT NULL,
    x REAL, y REAL, z REAL, qx REAL, qy REAL, qz REAL, qw REAL, robot TEXT NOT NULL,
    session TEXT NOT NULL, descriptor BLOB NOT NULL, dense_crc INTEGER NOT NULL,
    crc INTEGER NOT NULL, desc_crc INTEGER NOT NULL, camera INTEGER NOT NULL DEFAULT 0)""",
    "CREATE TABLE IF NOT EXISTS features (id INTEGER PRIMARY KEY, crc INTEGER NOT NULL, "
    "data BLOB NOT NULL)",
    "CREATE TABLE IF NOT EXISTS state (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
    *GROWTH_SCHEMA,
)
_META = "id, stamp, frame_id, source, x, y, z, qx, qy, qz, qw, robot, session"
_COLUMNS = _META + ", descriptor, dense_crc, crc, desc_crc"
_CHUNK = 4096  # rows per fetch when a load scans the table
# The rig camera of a keyframe (issue 49). Stores written before it have no such column: read,
# their keyframes are camera 0; the first keyframe of another camera added to one adds it
# (`_camera_column`, the one migration). A camera-0 row is written and checked as before it.
_CAMERA = "camera INTEGER NOT NULL DEFAULT 0"


def row_crc(row: tuple, camera: int = 0) -> int:
    """CRC32 of a keyframe row's values (all columns but `crc`, in _COLUMNS order), and of its
    camera when that is not 0 (so camera-0 rows keep the CRC they had before the column)."""
    *meta, desc, dense_crc = row
    # + 0.0: SQLite gives -0.0 back as 0.0 (a REAL of integral value is stored as an integer)
    meta = [v + 0.0 if isinstance(v, float) else v for v in meta] + ([camera] if camera else [])
    return zlib.crc32(desc + struct.pack("<I", dense_crc), zlib.crc32(repr(meta).encode()))


class KeyframeStore:
    """Keyframe rows of one map in the SQLite file `path`.

    saved: the file is a saved map's (WAL, durable commits, adds held in an open transaction
    until `commit`); otherwise a working file (no journal, every add committed at once).
    read_only: open a saved file for reading only.
    """

    def __init__(self, path: Path, *, saved: bool, read_only: bool = False) -> None:
        self.path, self.saved, self.read_only = Path(path), saved, read_only
        self.rolled_back = False  # a failed commit was rolled back by SQLite
        try:
            self._conn = self._connect()
        except sqlite3.OperationalError as err:
            if "locked" in str(err) or "busy" in str(err):
                raise MapError(
                    f"keyframe store {self.path} is being written by another process ({err}): "
                    "close that map first, or load this one with read_only=True"
                ) from err
            raise self.damaged(f"is not a readable SQLite database ({err})") from err
        except (sqlite3.Error, UnicodeDecodeError) as err:
            raise self.damaged(f"is not a readable SQLite database ({err})") from err
        self._has_camera: bool | None = None  # known once asked (`_camera_column`)

    def _camera_column(self, add: bool = False) -> bool:
        """Whether the keyframe table has the camera column; `add`: give it one (an old store
        taking its first keyframe of a camera other than 0; in the open transaction, so a
        rollback takes it back with the rows)."""
        if self._has_camera is None:
            rows = self._conn.execute("PRAGMA table_info(keyframes)").fetchall()
            self._has_camera = any(r[1] == "camera" for r in rows)
        if add and not self._has_camera:
            self._conn.execute(f"ALTER TABLE keyframes ADD COLUMN {_CAMERA}")
            self._has_camera = True
        return self._has_camera

    def _select(self) -> str:
        """The keyframe columns a read takes: _COLUMNS, then the camera (0 in an old store)."""
        try:
            return _COLUMNS + (", camera" if self._camera_column() else ", 0")
        except (sqlite3.Error, UnicodeDecodeError) as err:
            raise self.damaged(f"cannot be read ({err})") from err

    def _connect(self) -> sqlite3.Connection:
        # Callers serialise access (the pipeline's lock), so any thread may use the connection.
        # A saved file is only read and appended to: never given a schema or journal mode here
        # (a foreign or damaged file must stay as it is; copy_to makes the saved ones).
        if self.read_only:
            return self._connect_read_only()
        conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        if not self.saved:
            conn.execute("PRAGMA journal_mode=OFF")  # a working file: the save is durable
            conn.execute("PRAGMA synchronous=OFF")
            for statement in _SCHEMA:
                conn.execute(statement)
            return conn
        mode = conn.execute("PRAGMA journal_mode").fetchone()[0]
        if mode != "wal":
            conn.close()
            raise self.damaged(f"is not a saved keyframe store (journal mode {mode!r})")
        conn.execute("PRAGMA synchronous=FULL")  # a returned save survives a power cut
        conn.execute("PRAGMA wal_autocheckpoint=0")  # `checkpoint`, after a save, off its path
        conn.execute("BEGIN IMMEDIATE")  # a second writer fails here, not at its save
        return conn

    def _connect_read_only(self) -> sqlite3.Connection:
        """Without a writer (no -wal file), as an immutable file: nothing is created next to it
        (a read-only connection could not remove its -wal/-shm again) and read-only media work;
        with one, through the WAL, to see its last commit."""
        base = f"file:{quote(str(self.path))}?mode=ro"
        active = Path(f"{self.path}-wal").exists()
        for uri in (base, base + "&immutable=1") if active else (base + "&immutable=1",):
            conn = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False)
            try:
                conn.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()
                return conn
            except sqlite3.OperationalError:
                conn.close()
        raise self.damaged("cannot be opened for reading")

    def damaged(self, what: str) -> MapError:
        return MapError(
            f"keyframe store {self.path} {what}: the map is damaged; restore it from a backup "
            "or rebuild it"
        )

    # ------------------------------------------------------------------------ writing

    def add(self, meta: KeyframeMeta, desc: np.ndarray, dense_crc: int, features: bytes) -> None:
        """meta: validated, with its id set; desc [desc_dim] float32; features: b"" = none."""
        pose = meta.pose if meta.pose is not None else (None,) * 7
        values = (meta.id, meta.stamp, meta.frame_id, meta.source, *pose, meta.robot,
                  meta.session, np.asarray(desc, "<f4").tobytes(), int(dense_crc))  # fmt: skip
        cam = [meta.camera] if meta.camera and self._camera_column(add=True) else []
        self._conn.execute(
            f"INSERT INTO keyframes ({_COLUMNS}{', camera' * len(cam)}) "
            f"VALUES ({','.join('?' * (17 + len(cam)))})",
            (*values, row_crc(values, meta.camera), zlib.crc32(values[13]), *cam),
        )
        if features:
            self._conn.execute(
                "INSERT INTO features (id, crc, data) VALUES (?, ?, ?)",
                (meta.id, zlib.crc32(features), sqlite3.Binary(features)),
            )

    def delete_from(self, kf_id: int) -> None:
        """Remove rows with id >= kf_id (undo of a failed add)."""
        self._conn.execute("DELETE FROM keyframes WHERE id >= ?", (int(kf_id),))
        self._conn.execute("DELETE FROM features WHERE id >= ?", (int(kf_id),))

    def set_state(self, key: str, value: str) -> None:
        self._conn.execute("INSERT OR REPLACE INTO state (key, value) VALUES (?, ?)", (key, value))

    def commit(self) -> None:
        """Make every add since the last commit durable (the commit point of a save). A failed
        commit may leave the rows in the open transaction or (SQLite's choice on a full disk)
        roll them back: `in_transaction` tells which."""
        if not self.saved:
            return
        try:
            self._commit_sql()
        except BaseException:
            if not self._conn.in_transaction:
                self.rolled_back = True  # the caller drops the rows from the live map too
                self._has_camera = None  # a camera column added since went with them
                self._conn.execute("BEGIN IMMEDIATE")
            raise
        self._conn.execute("BEGIN IMMEDIATE")

    def _commit_sql(self) -> None:
        self._conn.execute("COMMIT")

    def checkpoint(self) -> None:
        """Fold the committed WAL into the database file through a second connection (PASSIVE:
        never waits for the writer), so it may run on another thread than the adds."""
        if not self.saved or self.read_only:
            return
        try:
            conn = sqlite3.connect(self.path, timeout=0.1)
            try:
                conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
            finally:
                conn.close()
        except sqlite3.Error:
            pass  # busy or gone (the map was cleared meanwhile): the next save's checkpoint

    def count(self) -> int:
        return int(self._one("SELECT COUNT(*) FROM keyframes")[0])

    def copy_to(self, path: Path, state: dict[str, str]) -> None:
        """Write every row (also uncommitted ones) into a new saved-format database `path`,
        with `state` replacing the state rows."""
        dst = sqlite3.connect(path, isolation_level=None)
        try:
            dst.execute("PRAGMA journal_mode=OFF")  # a new file: written, then fsynced whole
            for statement in _SCHEMA:
                dst.execute(statement)
            dst.execute("BEGIN")
            tables = [("keyframes", _COLUMNS + ", camera"), ("features", "id, crc, data")]
            if self.growth().present():  # a store written before them has none to copy
                tables += list(GROWTH_TABLES.items())
            for table, columns in tables:
                marks = ",".join("?" * len(columns.split(", ")))
                read = self._select() if table == "keyframes" else columns
                rows = self._conn.execute(f"SELECT {read} FROM {table} ORDER BY 1")
                while batch := rows.fetchmany(_CHUNK):
                    dst.executemany(f"INSERT INTO {table} ({columns}) VALUES ({marks})", batch)
            dst.executemany("INSERT INTO state (key, value) VALUES (?, ?)", state.items())
            dst.execute("COMMIT")
            dst.execute("PRAGMA journal_mode=WAL")  # persistent: saves append through the WAL
        finally:
            dst.close()

    # ------------------------------------------------------------------------ reading

    def state(self, key: str) -> str | None:
        row = self._one("SELECT value FROM state WHERE key = ?", key)
        return None if row is None else str(row[0])

    def count_checked(self) -> int:
        """The number of keyframe rows (ids 0..n-1) and no features row of another id: two
        lookups of the primary keys (no row is read)."""
        # one MIN or MAX a subquery: SQLite reads one end of the primary key for each
        lo, hi = self._one(
            "SELECT (SELECT MIN(id) FROM keyframes), (SELECT MAX(id) FROM keyframes)"
        )
        n = 0 if hi is None else int(hi) + 1
        if lo not in (0, None):  # rows missing further on: found when read (`get`, `scan`)
            raise self.damaged(f"holds keyframe rows with ids {lo}..{hi}: rows are missing")
        stray = self._one("SELECT COUNT(*) FROM features WHERE id < 0 OR id >= ?", n)[0]
        if stray:  # a range of the primary key: no feature bytes are read
            raise self.damaged(f"holds {stray} feature rows of no keyframe")
        return n

    def scan(self, desc_dim: int, start: int = 0) -> np.ndarray:
        """-> descriptors [n - start, desc_dim] float32 of keyframes start..n-1, each checked
        against its CRC32 (a row's other values are checked when read: `get`, `all`)."""
        n = self.count_checked()
        sql = "SELECT descriptor, desc_crc FROM keyframes WHERE id >= ? ORDER BY id"
        try:
            rows = self._conn.execute(sql, (start,)).fetchall()
            if len(rows) != n - start:
                got = f"{len(rows) + start} keyframe rows with ids 0..{n - 1}"
                raise self.damaged(f"holds {got}: rows are missing")
            for i, (blob, crc) in enumerate(rows, start):
                if zlib.crc32(blob) != crc:  # before the shape: a damaged row is named as one
                    raise self.damaged(f"holds keyframe {i} with a wrong CRC32 (a damaged row)")
            descs = np.frombuffer(b"".join(r[0] for r in rows), "<f4")
            return descs.reshape(n - start, desc_dim).astype(np.float32)
        except (sqlite3.Error, TypeError, ValueError, OverflowError) as err:
            raise self.damaged(f"cannot be read ({err})") from err

    def dense_crc(self, kf_id: int) -> int:
        """The CRC32 of keyframe `kf_id`'s dense entry, as its row holds it."""
        row = self._one("SELECT dense_crc FROM keyframes WHERE id = ?", int(kf_id))
        if row is None or not isinstance(row[0], int):
            raise self.damaged(f"has no dense CRC32 for keyframe {kf_id}")
        return row[0]

    def _rows(self, sql: str) -> Iterator[tuple]:
        try:
            cursor = self._conn.execute(sql)
            while batch := cursor.fetchmany(_CHUNK):
                yield from batch
        except (sqlite3.Error, UnicodeDecodeError) as err:  # a damaged page or text
            raise self.damaged(f"cannot be read ({err})") from err

    def _one(self, sql: str, *args) -> tuple | None:
        try:
            return self._conn.execute(sql, args).fetchone()
        except (sqlite3.Error, UnicodeDecodeError) as err:  # a damaged page or text
            raise self.damaged(f"cannot be read ({err})") from err

    def _check_row(self, row: tuple, kf_id: int) -> None:
        desc = row[13]
        if row[0] != kf_id or not isinstance(desc, bytes) or not isinstance(row[14], int):
            raise self.damaged(f"has a bad row where keyframe {kf_id} should be")
        if not isinstance(row[17], int) or row_crc(row[:15], row[17]) != row[15]:
            raise self.damaged(f"holds keyframe {kf_id} with a wrong CRC32 (a damaged row)")

    def get(self, kf_id: int) -> KeyframeMeta | None:
        row = self._one(f"SELECT {self._select()} FROM keyframes WHERE id = ?", int(kf_id))
        if row is None:
            return None
        self._check_row(row, int(kf_id))
        return _meta(row)

    def all(self) -> list[KeyframeMeta]:
        out = []
        rows = self._rows(f"SELECT {self._select()} FROM keyframes ORDER BY id")
        for kf_id, row in enumerate(rows):
            self._check_row(row, kf_id)
            out.append(_meta(row))
        return out

    def features(self, kf_id: int) -> bytes:
        """Packed features of keyframe `kf_id` (b"": none); MapError when they fail their CRC."""
        row = self._one("SELECT crc, data FROM features WHERE id = ?", int(kf_id))
        if row is None:
            return b""
        data = bytes(row[1]) if isinstance(row[1], bytes) else b""
        if not isinstance(row[1], bytes) or zlib.crc32(data) != row[0]:
            raise MapError(
                f"the features of keyframe {kf_id} fail their CRC32 check: the map is damaged; "
                "restore it from a backup or rebuild it"
            )
        return data

    def feature_stats(self) -> tuple[int, int]:
        """(keyframes with features, total bytes of their features)."""
        n, size = self._one("SELECT COUNT(*), SUM(LENGTH(data)) FROM features")
        return int(n), int(size or 0)

    def growth(self, writable: bool = True) -> GrowthTables:
        """The growth tables (signatures, links, represented keyframes) in this store."""
        return GrowthTables(self._conn, self.damaged, writable and not self.read_only)

    def close(self) -> None:
        """Roll back unsaved rows and close (the last connection folds the WAL into the file)."""
        try:
            if self._conn.in_transaction:
                self._conn.execute("ROLLBACK")
        except sqlite3.Error:
            pass  # closing rolls back as well
        self._conn.close()


def _meta(row: tuple) -> KeyframeMeta:
    kf_id, stamp, frame_id, source, *pose = row[:11]
    robot, session = row[11], row[12]
    pose_or_none = None if pose[0] is None else tuple(pose)
    return KeyframeMeta(kf_id, stamp, frame_id, pose_or_none, source, robot, session, row[17])
