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

import secrets
import sqlite3
import zlib
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import quote

import numpy as np

from pair_vpr_ros.errors import MapError, disk_full
from pair_vpr_ros.place_map import schema
from pair_vpr_ros.place_map.growth.tables import GrowthTables
from pair_vpr_ros.place_map.metadata import KeyframeMeta, identity_problem
from pair_vpr_ros.place_map.schema import COLUMNS as _COLUMNS
from pair_vpr_ros.place_map.schema import STORE_ID, row_crc

_CHUNK = 4096  # rows per fetch when a load scans the table


class KeyframeStore:
    """Keyframe rows of one map in the SQLite file `path`.

    saved: the file is a saved map's (WAL, durable commits, adds held in an open transaction
    until `commit`); otherwise a working file (no journal, every add committed at once).
    read_only: open a saved file for reading only; wal False: its file alone, without the
    rows of its write-ahead log (`-wal`) not yet folded into it.
    """

    def __init__(
        self, path: Path, *, saved: bool, read_only: bool = False, wal: bool = True
    ) -> None:
        self.path, self.saved, self.read_only = Path(path), saved, read_only or not wal
        self.rolled_back = False  # a failed commit was rolled back by SQLite
        self.wal_ignored = not wal  # its -wal exists but is not read (immutable open)
        self._checkpointed = True  # the WAL is folded in since the last commit
        self._clean_start = True  # the open transaction began on a folded-in WAL
        try:
            self._conn = self._connect(wal)
        except sqlite3.OperationalError as err:
            if "locked" in str(err) or "busy" in str(err):
                raise MapError(
                    f"keyframe store {self.path} is being written by another process ({err}): "
                    "close that map first, or load this one with read_only=True"
                ) from err
            raise self.failure(err, "is not a readable SQLite database") from err
        except (sqlite3.Error, UnicodeDecodeError) as err:
            raise self.failure(err, "is not a readable SQLite database") from err

    def failure(self, err: BaseException, what: str) -> MapError:
        """A failed SQLite call in words: a full disk (SQLITE_FULL: also SQLite's temporary
        files, in $TMPDIR) as one, anything else as a damaged store."""
        if disk_full(err):
            what = "cannot be opened" if what.startswith("is not") else what
            return MapError(
                f"keyframe store {self.path} {what}: the disk is full ({err}): free disk space "
                "there (SQLite also writes temporary files to $TMPDIR) and retry"
            )
        return self.damaged(f"{what} ({err})")

    def _connect(self, wal: bool) -> sqlite3.Connection:
        # Callers serialise access (the pipeline's lock), so any thread may use the connection.
        # A saved file is only read and appended to: never given a journal mode here (a foreign
        # or damaged file must stay as it is; copy_to makes the saved ones); a writable open
        # brings an older schema up to date in its open transaction (schema.py).
        if self.read_only:
            return self._connect_read_only(wal)
        conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        if not self.saved:
            conn.execute("PRAGMA journal_mode=OFF")  # a working file: the save is durable
            conn.execute("PRAGMA synchronous=OFF")
            schema.create(conn)
            return conn
        mode = conn.execute("PRAGMA journal_mode").fetchone()[0]
        if mode != "wal":
            conn.close()
            raise self.damaged(f"is not a saved keyframe store (journal mode {mode!r})")
        conn.execute("PRAGMA synchronous=FULL")  # a returned save survives a power cut
        conn.execute("PRAGMA wal_autocheckpoint=0")  # `checkpoint`, after a save, off its path
        # a WAL started afresh after a checkpoint is cut to the save that restarted it
        conn.execute("PRAGMA journal_size_limit=0")
        wal_file = Path(f"{self.path}-wal")  # frames left by a crash: folded in at the save
        self._clean_start = not (wal_file.exists() and wal_file.stat().st_size)
        conn.execute("BEGIN IMMEDIATE")  # a second writer fails here, not at its save
        try:
            schema.migrate(conn, self.path)
        except BaseException:
            conn.close()
            raise
        return conn

    def _connect_read_only(self, wal: bool) -> sqlite3.Connection:
        """Without a writer (no -wal file), as an immutable file: nothing is created next to it
        (a read-only connection could not remove its -wal/-shm again) and read-only media work;
        with one, through the WAL, to see its last commit."""
        base = f"file:{quote(str(self.path))}?mode=ro"
        active = wal and Path(f"{self.path}-wal").exists()
        for uri in (base, base + "&immutable=1") if active else (base + "&immutable=1",):
            conn = sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False)
            try:
                conn.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()
                schema.check_version(conn, self.path)
                self.wal_ignored = self.wal_ignored or (active and "immutable" in uri)
                return conn
            except sqlite3.OperationalError:
                conn.close()
            except MapError:
                conn.close()
                raise
        raise self.damaged("cannot be opened for reading")

    def damaged(self, what: str) -> MapError:
        return MapError(
            f"keyframe store {self.path} {what}: the map is damaged; restore it from a backup "
            "or rebuild it"
        )

    # ------------------------------------------------------------------------ writing

    def begin(self) -> None:
        """Open the write transaction of a saved store, when none is (after a commit, the next
        write opens it: a checkpoint that ran in between lets SQLite start the WAL afresh)."""
        if self.saved and not self.read_only and not self._conn.in_transaction:
            self._clean_start = self._checkpointed
            self._conn.execute("BEGIN IMMEDIATE")

    def add(self, meta: KeyframeMeta, desc: np.ndarray, dense_crc: int, features: bytes) -> None:
        """meta: validated, with its id set; desc [desc_dim] float32; features: b"" = none."""
        pose = meta.pose if meta.pose is not None else (None,) * 7
        values = (meta.id, meta.stamp, meta.frame_id, meta.source, *pose, meta.robot,
                  meta.session, np.asarray(desc, "<f4").tobytes(), int(dense_crc))  # fmt: skip
        self.begin()
        self._conn.execute(
            f"INSERT INTO keyframes ({_COLUMNS}) VALUES ({','.join('?' * 17)})",
            (*values, row_crc(values), zlib.crc32(values[13])),
        )
        if features:
            self._conn.execute(
                "INSERT INTO features (id, crc, data) VALUES (?, ?, ?)",
                (meta.id, zlib.crc32(features), sqlite3.Binary(features)),
            )

    def delete_from(self, kf_id: int) -> None:
        """Remove rows with id >= kf_id (undo of a failed add)."""
        self.begin()
        self._conn.execute("DELETE FROM keyframes WHERE id >= ?", (int(kf_id),))
        self._conn.execute("DELETE FROM features WHERE id >= ?", (int(kf_id),))

    def set_state(self, key: str, value: str) -> None:
        self.begin()
        self._conn.execute("INSERT OR REPLACE INTO state (key, value) VALUES (?, ?)", (key, value))

    def commit(self) -> None:
        """Make every add since the last commit durable (the commit point of a save). A failed
        commit may leave the rows in the open transaction or (SQLite's choice on a full disk)
        roll them back: `in_transaction` tells which. The next write opens the next
        transaction (`begin`); when this one began before the last save's rows were folded
        in (its checkpoint ran late), they are folded in here, so the WAL starts afresh."""
        if not self.saved:
            return
        self.begin()  # a save with nothing added still commits (and names its state)
        try:
            self._commit_sql()
        except BaseException:
            if not self._conn.in_transaction:
                self.rolled_back = True  # the caller drops the rows from the live map too
            raise
        self._checkpointed = False
        if not self._clean_start:
            self._fold(self._conn)

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
                self._fold(conn)
            finally:
                conn.close()
        except sqlite3.Error:
            pass  # busy or gone (the map was cleared meanwhile): the next save's checkpoint

    def _fold(self, conn: sqlite3.Connection) -> None:
        busy, log, done = conn.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
        self._checkpointed = self._checkpointed or (busy == 0 and log == done)

    @property
    def store_id(self) -> str:
        """The store's identity (state row; "" in a store written before issue 48)."""
        return self.state(STORE_ID) or ""

    def count(self) -> int:
        return int(self._one("SELECT COUNT(*) FROM keyframes")[0])

    def copy_to(self, path: Path, state: dict[str, str], dense_crcs=None) -> None:
        """Write every row (also uncommitted ones) into a new saved-format database `path`,
        with `state` replacing the state rows (a new generation: its own STORE_ID there) and,
        when given, `dense_crcs` [n] as the rows' dense CRC32s (a re-coded dense copy)."""
        schema.copy_store(self._conn, path, state, self.growth().present(), dense_crcs)

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
            raise self.failure(err, "cannot be read") from err

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
            raise self.failure(err, "cannot be read") from err

    def _one(self, sql: str, *args) -> tuple | None:
        try:
            return self._conn.execute(sql, args).fetchone()
        except (sqlite3.Error, UnicodeDecodeError) as err:  # a damaged page or text
            raise self.failure(err, "cannot be read") from err

    def _check_row(self, row: tuple, kf_id: int) -> None:
        desc = row[13]
        if row[0] != kf_id or not isinstance(desc, bytes) or not isinstance(row[14], int):
            raise self.damaged(f"has a bad row where keyframe {kf_id} should be")
        if row_crc(row[:15]) != row[15]:
            raise self.damaged(f"holds keyframe {kf_id} with a wrong CRC32 (a damaged row)")
        problem = identity_problem(str(row[11]), str(row[12]))
        if problem:  # a row written before names were checked: never passed on (issue 38)
            raise MapError(
                f"keyframe store {self.path}: keyframe {kf_id}'s {problem}; the map was written "
                "before robot and session names were checked: rebuild it with valid names"
            )

    def get(self, kf_id: int) -> KeyframeMeta | None:
        row = self._one(f"SELECT {_COLUMNS} FROM keyframes WHERE id = ?", int(kf_id))
        if row is None:
            return None
        self._check_row(row, int(kf_id))
        return _meta(row)

    def all(self) -> list[KeyframeMeta]:
        out = []
        for kf_id, row in enumerate(self._rows(f"SELECT {_COLUMNS} FROM keyframes ORDER BY id")):
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
        writable = writable and not self.read_only
        return GrowthTables(self._conn, self.damaged, writable, self.failure, self.begin)

    def close(self) -> None:
        """Roll back unsaved rows and close (the last connection folds the WAL into the file)."""
        try:
            if self._conn.in_transaction:
                self._conn.execute("ROLLBACK")
        except sqlite3.Error:
            pass  # closing rolls back as well
        self._conn.close()


def new_id() -> str:
    """A new store identity: 16 random hex digits."""
    return secrets.token_hex(8)


def _meta(row: tuple) -> KeyframeMeta:
    kf_id, stamp, frame_id, source, *pose = row[:11]
    robot, session = row[11], row[12]
    pose_or_none = None if pose[0] is None else tuple(pose)
    return KeyframeMeta(kf_id, stamp, frame_id, pose_or_none, source, robot, session)
