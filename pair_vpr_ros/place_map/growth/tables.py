"""The growth tables of a keyframe store (SQLite, the same database and transaction as the
keyframe rows, so a save commits them together and a kill -9 rolls them back together):

- `signatures`: per stored keyframe, its appearance signature (float16 [S], loops/growth.py);
- `links`: two stored keyframes joined by an accepted loop with a confident relative pose,
  `T_b_a` (keyframe a's camera in keyframe b's optical frame, x y z qx qy qz qw), and the
  re-rank score with which keyframe a's query recognised b (NULL: not known, a link written
  before issue 48; compact's recognition rule, compact.py);
- `represented`: a keyframe that was not stored because a stored one already represents its
  place and appearance: its stamp, robot, session, the representative's id and the distance of
  their signatures.

Every row carries a CRC32 of its values, checked when read (MapError: a damaged row). A saved
store written before these tables has none: they are created inside the map's open write
transaction by the first write (so only a save makes them durable) and read as empty until then.
"""

from __future__ import annotations

import math
import sqlite3
import zlib
from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map.schema import GROWTH_SCHEMA, GROWTH_TABLES, has_column


def _crc(values: tuple) -> int:
    """CRC32 of a row's values (blobs as bytes, floats + 0.0 as SQLite gives -0.0 back)."""
    parts = [v if isinstance(v, bytes) else repr(v + 0.0 if isinstance(v, float) else v).encode()
             for v in values]  # fmt: skip
    return zlib.crc32(b"\x1f".join(parts))


@dataclass(frozen=True)
class Represented:
    """A keyframe not stored: its stamp (s), robot, session, and who represents it."""

    stamp: float
    robot: str
    session: str
    representative: int
    distance: float


@dataclass(frozen=True)
class GrowthCounts:
    """Rows of each growth table: keyframes with a signature, links, represented keyframes."""

    signatures: int = 0
    links: int = 0
    represented: int = 0


class GrowthTables:
    """The growth tables of one open keyframe store (`KeyframeStore.growth()`): `conn` is the
    store's connection (its open transaction, when it has one), `damaged` its error maker for
    a damaged row, `failure(err, what)` for a failed SQLite call (a full disk said as one),
    `begin` opens the store's write transaction (when it has none) before a write."""

    def __init__(
        self, conn: sqlite3.Connection, damaged, writable: bool, failure=None, begin=None
    ) -> None:
        self._conn, self._damaged, self._writable = conn, damaged, writable
        self._failure = failure or (lambda err, what: damaged(f"{what} ({err})"))
        self._begin = begin or (lambda: None)

    # ------------------------------------------------------------------------ writing

    def _write(self, sql: str, values: tuple, crc_of: tuple | None = None) -> None:
        if not self._writable:
            raise MapError("cannot record growth rows in a map loaded with read_only=True")
        try:
            self._begin()
            if not self.present():
                for statement in GROWTH_SCHEMA:  # inside the open transaction: durable at save
                    self._conn.execute(statement)
            self._conn.execute(sql, (*values, _crc(values if crc_of is None else crc_of)))
        except sqlite3.Error as err:  # a full disk: the keyframe rows' own error, said alike
            raise self._failure(err, "could not record a growth row") from err

    def add_signature(self, kf_id: int, signature: np.ndarray) -> None:
        """signature [S] float (stored float16)."""
        data = np.asarray(signature, "<f2").tobytes()
        self._write("INSERT OR REPLACE INTO signatures (id, data, crc) VALUES (?, ?, ?)",
                    (int(kf_id), data))  # fmt: skip

    def add_link(
        self, a: int, b: int, pose: tuple[float, ...], score: float | None = None
    ) -> None:
        """Keyframes a and b (a != b) joined by a posed loop; pose: T_b_a (x y z qx qy qz qw);
        score: the re-rank score of b for a's query (None / NaN: not known)."""
        values = (int(a), int(b), *(float(v) for v in pose))
        known = score is not None and math.isfinite(float(score))
        scored = (*values, float(score)) if known else values  # a row's CRC covers its score
        self._write("INSERT OR REPLACE INTO links (a, b, tx, ty, tz, qx, qy, qz, qw, score, crc) "
                    f"VALUES ({','.join('?' * 11)})", (*values, scored[9] if known else None),
                    scored)  # fmt: skip

    def add_represented(self, row: Represented) -> None:
        values = (float(row.stamp), row.robot, row.session, int(row.representative),
                  float(row.distance))  # fmt: skip
        self._write(f"INSERT INTO represented ({GROWTH_TABLES['represented']}) VALUES "
                    f"({','.join('?' * 6)})", values)  # fmt: skip

    # ------------------------------------------------------------------------ reading

    def present(self) -> bool:
        """Whether the store has the growth tables (a store written before them has not)."""
        row = self._one("SELECT COUNT(*) FROM sqlite_master WHERE type='table' AND "
                        "name IN ('signatures', 'links', 'represented')")  # fmt: skip
        return row is not None and row[0] == 3

    def signature(self, kf_id: int) -> np.ndarray | None:
        """The signature [S] float32 of a stored keyframe (None: it has none)."""
        row = self._one("SELECT id, data, crc FROM signatures WHERE id = ?", int(kf_id))
        if row is None:
            return None
        self._check(row, f"the signature of keyframe {kf_id}")
        return np.frombuffer(row[1], "<f2").astype(np.float32)

    def links(self, kf_id: int) -> list[tuple[int, tuple[float, ...]]]:
        """Keyframes linked to `kf_id`: (other id, T_other_kf as x y z qx qy qz qw) each,
        read from either end of the link (the pose inverted where `kf_id` is its `b`)."""
        return [(other, pose) for other, pose, _ in self.scored_links(kf_id)]

    def scored_links(self, kf_id: int) -> list[tuple[int, tuple[float, ...], float | None]]:
        """`links`, each with the re-rank score of the link's `b` for its `a`'s query (None:
        not known: a link written before issue 48, or by a merge of such a map)."""
        score = "score" if self._scored() else "NULL"
        rows = self._all(f"SELECT a, b, tx, ty, tz, qx, qy, qz, qw, crc, {score} FROM links "
                         "WHERE a = ? OR b = ? ORDER BY a, b", int(kf_id), int(kf_id))  # fmt: skip
        out = []
        for row in rows:
            values = row[:9] if row[10] is None else (*row[:9], row[10])
            self._check((*values, row[9]), f"the link of keyframes {row[0]} and {row[1]}")
            pose = tuple(float(v) for v in row[2:9])
            kept = (row[1], pose) if row[0] == kf_id else (row[0], invert(pose))
            out.append((*kept, None if row[10] is None else float(row[10])))
        return out

    def _scored(self) -> bool:
        """The links table has the score column (a store migrated or written since issue 48;
        a read-only open of an older one has not)."""
        if getattr(self, "_has_score", None) is None:
            if not self.present():
                return True  # no rows: a first one makes the table with the column
            self._has_score = has_column(self._conn, "links", "score")
        return self._has_score

    def represented(self) -> list[Represented]:
        rows = self._all(f"SELECT {GROWTH_TABLES['represented']} FROM represented ORDER BY rowid")
        for row in rows:
            self._check(row, f"the represented keyframe at stamp {row[0]}")
        return [Represented(*row[:5]) for row in rows]

    def counts(self) -> GrowthCounts:
        if not self.present():
            return GrowthCounts()
        found = [self._one(f"SELECT COUNT(*) FROM {t}")[0] for t in GROWTH_TABLES]
        return GrowthCounts(*(int(n) for n in found))

    def _check(self, row: tuple, what: str) -> None:
        if _crc(tuple(row[:-1])) != row[-1]:
            raise self._damaged(f"holds {what} with a wrong CRC32 (a damaged row)")

    def _one(self, sql: str, *args) -> tuple | None:
        try:
            return self._conn.execute(sql, args).fetchone()
        except (sqlite3.Error, UnicodeDecodeError) as err:
            raise self._failure(err, "cannot be read") from err

    def _all(self, sql: str, *args) -> list[tuple]:
        if not self.present():
            return []
        try:
            return self._conn.execute(sql, args).fetchall()
        except (sqlite3.Error, UnicodeDecodeError) as err:
            raise self._failure(err, "cannot be read") from err


def invert(pose: tuple[float, ...]) -> tuple[float, ...]:
    """T (x y z qx qy qz qw, unit quaternion) -> T^-1 in the same form."""
    t, (qx, qy, qz, qw) = np.asarray(pose[:3]), pose[3:7]
    inv = (-qx, -qy, -qz, qw)
    return (*(-rotate(inv, t)), *inv)


def compose(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, ...]:
    """T_a * T_b, each x y z qx qy qz qw."""
    ax, ay, az, aw = a[3:7]
    bx, by, bz, bw = b[3:7]
    q = (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
         aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)  # fmt: skip
    t = np.asarray(a[:3]) + rotate(a[3:7], np.asarray(b[:3]))
    return (*(float(v) for v in t), *q)


def rotate(q: tuple[float, ...], v: np.ndarray) -> np.ndarray:
    """Rotate the 3-vector v by the unit quaternion q (x y z w)."""
    u, w = np.asarray(q[:3], dtype=np.float64), float(q[3])
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)
