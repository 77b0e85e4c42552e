"""The keyframe store's SQL schema (store.py), its version, and the migration of older stores:
the one place where a column is added.

A store records its schema version in SQLite's `user_version`: 0 for the stores of format 3
(written before issue 48), `SCHEMA_VERSION` for a store written now. `migrate` brings a store
opened for writing up to `SCHEMA_VERSION` inside its open write transaction, so the next save
commits the change together with the keyframes (a kill -9 before it rolls both back); readers
take stores of every version up to `SCHEMA_VERSION` (`has_column` says whether a table has an
added column) and refuse a newer one. To add a column: append a step to `MIGRATIONS` (the
version it makes, the table, the column and its declaration), add the column to the table's
CREATE statement below (or the growth tables', growth/tables.py), and read it where
`has_column` says it is there (NULL in rows written before it).
"""

from __future__ import annotations

import sqlite3
import struct
import zlib

from pair_vpr_ros.errors import MapError

SCHEMA_VERSION = 1
# Each step: (the version it makes, table, column, declaration). A table that does not exist
# yet is created later with every column (its CREATE statement), so it needs no step.
MIGRATIONS: tuple[tuple[int, str, str, str], ...] = (
    (1, "links", "score", "REAL"),  # issue 48: the re-rank score that made the growth link
)
STORE_ID = "store_id"  # the `state` key of the store's identity (named by manifest.json)

KEYFRAMES_SCHEMA = (
    """CREATE TABLE IF NOT EXISTS keyframes (
    id INTEGER PRIMARY KEY, stamp REAL NOT NULL, frame_id TEXT NOT NULL, source TEXT NOT NULL,
    x REAL, y REAL, z REAL, qx REAL, qy REAL, qz REAL, qw REAL, robot TEXT NOT NULL,
    session TEXT NOT NULL, descriptor BLOB NOT NULL, dense_crc INTEGER NOT NULL,
    crc INTEGER NOT NULL, desc_crc INTEGER NOT NULL)""",
    "CREATE TABLE IF NOT EXISTS features (id INTEGER PRIMARY KEY, crc INTEGER NOT NULL, "
    "data BLOB NOT NULL)",
    "CREATE TABLE IF NOT EXISTS state (key TEXT PRIMARY KEY, value TEXT NOT NULL)",
)
# The growth tables (growth/tables.py): signatures, links (with the re-rank score that made
# the link since schema version 1; NULL in rows written before) and represented keyframes
GROWTH_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS signatures (id INTEGER PRIMARY KEY, data BLOB NOT NULL, "
    "crc INTEGER NOT NULL)",
    "CREATE TABLE IF NOT EXISTS links (a INTEGER NOT NULL, b INTEGER NOT NULL, tx REAL, ty REAL, "
    "tz REAL, qx REAL, qy REAL, qz REAL, qw REAL, crc INTEGER NOT NULL, score REAL, "
    "PRIMARY KEY (a, b))",
    "CREATE INDEX IF NOT EXISTS links_b ON links (b)",
    "CREATE TABLE IF NOT EXISTS represented (stamp REAL NOT NULL, robot TEXT NOT NULL, "
    "session TEXT NOT NULL, representative INTEGER NOT NULL, distance REAL NOT NULL, "
    "crc INTEGER NOT NULL)",
)
# table -> its columns, in the order a copy writes them
GROWTH_TABLES = {
    "signatures": "id, data, crc",
    "links": "a, b, tx, ty, tz, qx, qy, qz, qw, crc, score",
    "represented": "stamp, robot, session, representative, distance, crc",
}
META = "id, stamp, frame_id, source, x, y, z, qx, qy, qz, qw, robot, session"
COLUMNS = META + ", descriptor, dense_crc, crc, desc_crc"


def row_crc(row: tuple) -> int:
    """CRC32 of a keyframe row's values (all columns but `crc`, in COLUMNS order)."""
    *meta, desc, dense_crc = row
    # + 0.0: SQLite gives -0.0 back as 0.0 (a REAL of integral value is stored as an integer)
    meta = [v + 0.0 if isinstance(v, float) else v for v in meta]
    return zlib.crc32(desc + struct.pack("<I", dense_crc), zlib.crc32(repr(meta).encode()))


def create(conn: sqlite3.Connection, growth: bool = True) -> None:
    """Give a new store every table (growth False: not the growth tables, made by their first
    row) at the current version."""
    for statement in KEYFRAMES_SCHEMA + (GROWTH_SCHEMA if growth else ()):
        conn.execute(statement)
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")


def version(conn: sqlite3.Connection) -> int:
    return int(conn.execute("PRAGMA user_version").fetchone()[0])


def check_version(conn: sqlite3.Connection, path: object) -> int:
    """The store's schema version; MapError for one newer than this code reads."""
    found = version(conn)
    if found > SCHEMA_VERSION:
        raise MapError(
            f"keyframe store {path} has schema version {found}, this pair_vpr_ros reads up to "
            f"{SCHEMA_VERSION}: it was written by a newer pair_vpr_ros; use that release"
        )
    return found


def has_column(conn: sqlite3.Connection, table: str, column: str) -> bool:
    return any(row[1] == column for row in conn.execute(f"PRAGMA table_info({table})"))


def migrate(conn: sqlite3.Connection, path: object) -> None:
    """Bring the store to SCHEMA_VERSION inside the connection's open write transaction."""
    found = check_version(conn, path)
    if found == SCHEMA_VERSION:
        return
    for made, table, column, declaration in MIGRATIONS:
        exists = conn.execute(
            "SELECT COUNT(*) FROM sqlite_master WHERE type = 'table' AND name = ?", (table,)
        ).fetchone()[0]
        if made > found and exists and not has_column(conn, table, column):
            conn.execute(f"ALTER TABLE {table} ADD COLUMN {column} {declaration}")
    conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION}")


def copy_store(
    src: sqlite3.Connection, path: object, state: dict[str, str], growth: bool, dense_crcs=None
) -> None:
    """Write every row `src` sees (its open transaction's too) into a new store at `path` of the
    current version, with `state` as its state rows; growth: copy the growth tables (a store
    written before them has none); dense_crcs [n]: each keyframe row's new dense CRC32 (its
    row CRC32 made again)."""
    dst = sqlite3.connect(path, isolation_level=None)
    try:
        dst.execute("PRAGMA journal_mode=OFF")  # a new file: written, then fsynced whole
        create(dst)
        dst.execute("BEGIN")
        tables = [("keyframes", COLUMNS), ("features", "id, crc, data")]
        tables += list(GROWTH_TABLES.items()) if growth else []
        for table, columns in tables:
            marks = ",".join("?" * len(columns.split(", ")))
            rows = src.execute(f"SELECT {columns} FROM {table} ORDER BY 1")
            while batch := rows.fetchmany(4096):
                if table == "keyframes" and dense_crcs is not None:
                    batch = [_with_dense_crc(row, dense_crcs[row[0]]) for row in batch]
                dst.executemany(f"INSERT INTO {table} ({columns}) VALUES ({marks})", batch)
        dst.executemany("INSERT INTO state (key, value) VALUES (?, ?)", state.items())
        dst.execute("COMMIT")
        dst.execute("PRAGMA journal_mode=WAL")  # persistent: saves append through the WAL
    finally:
        dst.close()


def _with_dense_crc(row: tuple, crc: int) -> tuple:
    """A keyframe row (COLUMNS order) with another dense CRC32, its row CRC32 made again (a row
    that fails its own check keeps a failing one: damage is never laundered)."""
    values = (*row[:14], int(crc))
    intact = row_crc(row[:15]) == row[15]
    return (*values, row_crc(values) if intact else row[15] ^ 1, row[16])
