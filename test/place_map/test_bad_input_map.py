"""Bad-input matrix, map folders of format 2 (test/data/maps, written before issue 34; still
loaded): every file missing, truncated, corrupted, of the wrong schema or fingerprint gives a
MapError naming it, and no load changes a byte of the saved map. Format 3 (the store, saves,
full disks, two writers, the pipeline): test_bad_input_map_store.py."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
import struct
from pathlib import Path

import faiss
import numpy as np
import pytest
from bad_input import tree_digest
from test_place_map_persist import DIM, N0, SHAPE, add_range, flip_byte

from pair_vpr_ros.errors import MapError, MapFingerprintError
from pair_vpr_ros.hashing import sha256_file
from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap

MAPS = Path(__file__).parents[1] / "data" / "maps"  # written by pair_vpr_ros at cc01a8d


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    """A format-2 map of N0 keyframes (test_place_map_persist's content) in tmp_path / "map"."""
    return Path(shutil.copytree(MAPS / "format-2", tmp_path / "map"))


def _rewrite_manifest(d: Path, edit) -> None:
    data = json.loads((d / "manifest.json").read_text())
    edit(data)
    (d / "manifest.json").write_text(json.dumps(data))


def _file(d: Path, role: str) -> Path:
    return d / json.loads((d / "manifest.json").read_text())["files"][role]["name"]


def _replace_checked(d: Path, role: str, content: bytes) -> None:
    """Overwrite a checksummed file and fix its checksum, to reach the deeper checks."""
    path = _file(d, role)
    path.write_bytes(content)
    size, digest = len(content), sha256_file(path)
    _rewrite_manifest(d, lambda m: m["files"][role].update(size=size, sha256=digest))


def _truncate(d: Path, role: str, keep: float) -> None:
    path = _file(d, role)
    os.truncate(path, int(path.stat().st_size * keep))


def _sqlite(d: Path, *statements: str) -> None:
    """Replace the metadata file by a database made of `statements` (checksum fixed)."""
    tmp = d.parent / "other.sqlite"
    with sqlite3.connect(tmp) as conn:
        for sql in statements:
            conn.execute(sql)
    conn.close()
    _replace_checked(d, "meta", tmp.read_bytes())


GOOD_TABLE = (
    "CREATE TABLE keyframes (id INTEGER PRIMARY KEY, stamp REAL NOT NULL, frame_id TEXT NOT "
    "NULL, source TEXT NOT NULL, x REAL, y REAL, z REAL, qx REAL, qy REAL, qz REAL, qw REAL, "
    "robot TEXT NOT NULL, session TEXT NOT NULL)"
)


def _rows(count: int, stamp: str = "1.5") -> list[str]:
    return [
        f"INSERT INTO keyframes VALUES ({i}, {stamp}, 'cam', 's', NULL, NULL, NULL, NULL, "
        "NULL, NULL, NULL, 'robot', 'default')"
        for i in range(count)
    ]


def _faiss_size_field(d: Path, value: int) -> None:
    """A flat index whose vector-size field (byte 37) claims `value` floats."""
    data = bytearray(_file(d, "index").read_bytes())
    data[37:45] = struct.pack("<Q", value)
    _replace_checked(d, "index", bytes(data))


def _faiss(d: Path, index: faiss.Index) -> None:
    tmp = d.parent / "other.faiss"
    faiss.write_index(index, str(tmp))
    _replace_checked(d, "index", tmp.read_bytes())


def _flat(dim: int, count: int) -> faiss.Index:
    index = faiss.IndexFlatIP(dim)
    index.add(np.eye(max(dim, count), dim, dtype=np.float32)[:count])
    return index


def _crc_values(d: Path) -> None:
    """CRC32s of other data (size and checksum of the .crc file fixed)."""
    count = json.loads((d / MANIFEST).read_text())["count"]
    _replace_checked(d, "dense_crc", np.arange(count, dtype="<u4").tobytes())


MANIFEST = "manifest.json"
CORRUPTIONS = {
    # ---- manifest
    "no manifest": (lambda d: (d / MANIFEST).unlink(), r"manifest.json is missing"),
    "empty manifest": (lambda d: (d / MANIFEST).write_bytes(b""), r"is not valid JSON"),
    "bad json": (lambda d: (d / MANIFEST).write_text("{oops"), r"is not valid JSON"),
    "binary manifest": (lambda d: (d / MANIFEST).write_bytes(b"\xff\xfe\x00"), "not valid JSON"),
    "manifest list": (lambda d: (d / MANIFEST).write_text("[1, 2]"), r"no format field"),
    "manifest folder": (
        lambda d: ((d / MANIFEST).unlink(), (d / MANIFEST).mkdir()),
        r"manifest.json is missing",
    ),
    "version": (
        lambda d: _rewrite_manifest(d, lambda m: m.update(format_version=99)),
        r"has format_version 99, this version of pair_vpr_ros reads versions 1, 2, 3, 4: use a "
        r"matching pair_vpr_ros release or rebuild the map",
    ),
    "field": (
        lambda d: _rewrite_manifest(d, lambda m: m.pop("count")),
        r"has missing or invalid fields",
    ),
    "count text": (
        lambda d: _rewrite_manifest(d, lambda m: m.update(count="12")),
        r"invalid fields \(generation/count must be integers >= 0\)",
    ),
    "count negative": (
        lambda d: _rewrite_manifest(d, lambda m: m.update(count=-1)),
        r"invalid fields \(generation/count must be integers >= 0\)",
    ),
    "dense_shape zero": (
        lambda d: _rewrite_manifest(d, lambda m: m.update(dense_shape=[0, 8])),
        r"dense_shape entries must be integers > 0",
    ),
    "files not a dict": (
        lambda d: _rewrite_manifest(d, lambda m: m.update(files=[])),
        r"has missing or invalid fields",
    ),
    "file name": (
        lambda d: _rewrite_manifest(d, lambda m: m["files"]["meta"].update(name="../meta.db")),
        r"has missing or invalid fields \(bad file name for meta: '../meta.db'\)",
    ),
    "index settings": (
        lambda d: _rewrite_manifest(d, lambda m: m["index"].update(kind="pq")),
        r"manifest index settings .* are invalid .*must be one of",
    ),
    "more keyframes than stored": (
        lambda d: _rewrite_manifest(d, lambda m: m.update(count=N0 + 1)),
        r"index-1.faiss holds 12 vectors, the map lists 13 keyframes",
    ),
    # Issue 13 #2: a smaller dense_shape used to truncate the dense file on a writable load.
    "dense_shape smaller": (
        lambda d: _rewrite_manifest(d, lambda m: m.update(dense_shape=[2, 8])),
        r"dense-1.f16 does not match its manifest: keyframe 0 fails its CRC32 check when read "
        r"as \[2, 8\] f16 tokens .* nothing was changed",
    ),
    "dense_shape larger": (
        lambda d: _rewrite_manifest(d, lambda m: m.update(dense_shape=[8, 8])),
        r"dense-1.f16 is too short: 768 bytes hold 6 keyframes, the manifest lists 12",
    ),
    # ---- every file missing
    "missing index": (
        lambda d: _file(d, "index").unlink(),
        r"index-1.faiss \(index\) listed in .*manifest.json is missing",
    ),
    "missing meta": (lambda d: _file(d, "meta").unlink(), r"meta-1.sqlite \(meta\) .* is missing"),
    "missing crc": (
        lambda d: _file(d, "dense_crc").unlink(),
        r"dense-1.crc \(dense_crc\) .* is missing",
    ),
    "missing dense": (lambda d: _file(d, "dense").unlink(), r"dense-1.f16 \(dense\) .* missing"),
    "dense is a folder": (
        lambda d: (_file(d, "dense").unlink(), _file(d, "dense").mkdir()),
        r"dense-1.f16 \(dense\) .* is missing",
    ),
    # ---- truncated or flipped (checksums)
    "index truncated": (
        lambda d: _truncate(d, "index", 0.5),
        r"index-1.faiss \(index\) does not match its checksum",
    ),
    "meta truncated": (
        lambda d: _truncate(d, "meta", 0.5),
        r"meta-1.sqlite \(meta\) does not match its checksum",
    ),
    "crc truncated": (
        lambda d: _truncate(d, "dense_crc", 0.5),
        r"dense-1.crc \(dense_crc\) does not match its checksum",
    ),
    "index flipped": (
        lambda d: flip_byte(d / "index-1.faiss", 40),
        r"index-1.faiss \(index\) does not match its checksum",
    ),
    "meta flipped": (
        lambda d: flip_byte(d / "meta-1.sqlite", 200),
        r"meta-1.sqlite \(meta\) does not match its checksum",
    ),
    "short dense": (
        lambda d: os.truncate(d / "dense-1.f16", 11 * 64 + 5),
        r"dense token file .*dense-1.f16 is too short: 709 bytes hold 11 keyframes",
    ),
    "empty dense": (
        lambda d: os.truncate(d / "dense-1.f16", 0),
        r"dense-1.f16 is too short: 0 bytes hold 0 keyframes",
    ),
    "last dense entry flipped": (
        lambda d: flip_byte(d / "dense-1.f16", N0 * 64 - 1),
        r"keyframe 11 fails its CRC32 check when read as \[4, 8\]",
    ),
    # ---- checksums fixed: the deeper checks
    "index garbage": (
        lambda d: _replace_checked(d, "index", b"garbage" * 10),
        r"FAISS index .*index-1.faiss could not be read",
    ),
    "index empty": (
        lambda d: _replace_checked(d, "index", b""),
        r"FAISS index .*index-1.faiss could not be read",
    ),
    "faiss absurd size": (
        lambda d: _faiss_size_field(d, 1 << 35),  # 128 GiB: used to raise MemoryError
        r"index-1.faiss could not be read \(an array size field exceeds the file size\)",
    ),
    "faiss size past file": (
        lambda d: _faiss_size_field(d, 1 << 20),  # 4 MiB: allocated, then a short read
        r"index-1.faiss could not be read \(an array size field exceeds the file size\)",
    ),
    "faiss other dim": (
        lambda d: _faiss(d, _flat(DIM + 1, N0)),
        r"is a IndexFlatIP of dim 9, but the manifest says 'flat' of dim 8",
    ),
    "faiss hnsw for flat": (
        lambda d: _faiss(d, faiss.IndexHNSWFlat(DIM, 4, faiss.METRIC_INNER_PRODUCT)),
        r"is a IndexHNSWFlat of dim 8, but the manifest says 'flat'",
    ),
    "faiss l2": (
        lambda d: _faiss(d, faiss.IndexFlatL2(DIM)),
        r"is a IndexFlatL2 of dim 8, but the manifest says 'flat'",
    ),
    "faiss fewer vectors": (
        lambda d: _faiss(d, _flat(DIM, 3)),
        r"holds 3 vectors, the map lists 12 keyframes",
    ),
    "sqlite garbage": (
        lambda d: _replace_checked(d, "meta", b"not a database" * 100),
        r"keyframe metadata .*meta-1.sqlite is not a readable SQLite database",
    ),
    "sqlite empty file": (
        lambda d: _replace_checked(d, "meta", b""),
        r"meta-1.sqlite holds 0 rows \(ids None..None\), the manifest lists 12",
    ),
    "sqlite other table": (
        lambda d: _sqlite(d, "CREATE TABLE notes (t TEXT)"),
        r"meta-1.sqlite holds 0 rows",
    ),
    "sqlite wrong columns": (
        lambda d: _sqlite(d, "CREATE TABLE keyframes (id INTEGER PRIMARY KEY, stamp REAL)"),
        r"meta-1.sqlite is not a place map's keyframe table \(columns \['id', 'stamp'\]",
    ),
    "sqlite wrong types": (
        lambda d: _sqlite(d, GOOD_TABLE, *_rows(N0, stamp="'noon'")),
        r"meta-1.sqlite is not a place map's keyframe table \(12 rows hold values of wrong type",
    ),
    "sqlite half a pose": (
        lambda d: _sqlite(d, GOOD_TABLE, *_rows(N0), "UPDATE keyframes SET x = 1 WHERE id = 3"),
        r"keyframe table \(1 rows hold values of wrong type",
    ),
    "sqlite too many rows": (
        lambda d: _sqlite(d, GOOD_TABLE, *_rows(N0 + 1)),
        r"meta-1.sqlite holds 13 rows \(ids 0..12\), the manifest lists 12",
    ),
    "sqlite ids with a gap": (
        lambda d: _sqlite(d, GOOD_TABLE, *_rows(N0), "UPDATE keyframes SET id = 99 WHERE id = 4"),
        r"holds 12 rows \(ids 0..99\), the manifest lists 12",
    ),
    "crc count": (
        lambda d: _replace_checked(d, "dense_crc", b"\0" * 8),
        r"dense checksum file .*dense-1.crc holds 2 entries, the manifest lists 12",
    ),
    "crc values": (_crc_values, r"dense-1.f16 does not match its manifest: keyframe 0 fails"),
}


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_damaged_map_gives_map_error_and_stays_unchanged(saved: Path, case: str) -> None:
    damage, message = CORRUPTIONS[case]
    damage(saved)
    before = tree_digest(saved)
    with pytest.raises(MapError, match=message):
        PlaceMap.load(saved)
    with pytest.raises(MapError, match=message):  # a failed load released the lock
        PlaceMap.load(saved, read_only=True)
    assert tree_digest(saved) == before


def test_wrong_fingerprint_is_refused_and_unchanged(saved: Path) -> None:
    before = tree_digest(saved)
    with pytest.raises(MapFingerprintError, match="built with model fingerprint 'fp-a'"):
        PlaceMap.load(saved, expected_fingerprint="fp-b")
    assert tree_digest(saved) == before


# ---- Issue 38 #8: a full disk while a keyframe's metadata is written is a MapError, even
# when undoing the half-written rows fails too; the map keeps what it held.
@pytest.mark.parametrize("undo_fails", [False, True])
def test_a_full_disk_during_add_is_a_map_error(tmp_path, monkeypatch, undo_fails):
    from test_place_map_persist import dense_for, desc_for, meta_for

    with PlaceMap(DIM, SHAPE, "fp-a", work_dir=tmp_path) as m:
        add_range(m, 0, 3)
        store = m._store

        def full(*args):
            raise sqlite3.OperationalError("database or disk is full")

        def malformed(*args):
            raise sqlite3.DatabaseError("database disk image is malformed")

        monkeypatch.setattr(store, "add", full)
        if undo_fails:
            monkeypatch.setattr(store, "delete_from", malformed)
        with pytest.raises(MapError) as err:
            m.add(desc_for(3), dense_for(3), meta_for(3))
        if undo_fails:  # the store may hold part of it: the node's last save is the way back
            tail = ("; undoing it failed too (database disk image is malformed): its rows may be "
                    "half written; save nothing more and load the map's last save")  # fmt: skip
        else:
            tail = "; the map keeps its 3 keyframes: free disk space and go on"
        assert str(err.value) == (
            f"storing keyframe 3 failed: the disk is full (database or disk is full){tail}"
        )
        monkeypatch.undo()
        assert len(m) == 3 and m.add(desc_for(3), dense_for(3), meta_for(3)) == 3


# ---- issue 48, loose end 4: robot and session names of a map's keyframes follow the identity
# rule (identity.py): a new keyframe is refused, an old map's rows are named, never passed on.
def test_a_keyframe_named_against_the_rule_is_refused(tmp_path) -> None:
    from test_place_map_persist import dense_for, desc_for

    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        with pytest.raises(MapError) as err:
            m.add(desc_for(0), dense_for(0), KeyframeMeta(stamp=1.0, robot="a/b", session="s"))
        assert len(m) == 0
    assert str(err.value) == (
        "keyframe metadata: robot 'a/b' must be 1-64 characters of ASCII letters, digits or '_' "
        "(a robot id starts with a letter): it names folders, a ROS topic and pose-graph keys, "
        "e.g. robot1"
    )


def test_an_old_maps_names_against_the_rule_are_refused_at_load(tmp_path) -> None:
    """A format-2 map written before the rule, a keyframe of session '..': its load says so."""
    import hashlib

    d = Path(shutil.copytree(MAPS / "format-2", tmp_path / "map"))
    conn = sqlite3.connect(d / "meta-1.sqlite")
    with conn:
        conn.execute("UPDATE keyframes SET robot = 'r1', session = '..' WHERE id = 4")
    conn.close()
    data = json.loads((d / "manifest.json").read_text())
    meta = d / "meta-1.sqlite"
    data["files"]["meta"].update(
        size=meta.stat().st_size, sha256=hashlib.sha256(meta.read_bytes()).hexdigest()
    )
    (d / "manifest.json").write_text(json.dumps(data))
    before = tree_digest(d)
    with pytest.raises(MapError) as err:
        PlaceMap.load(d, read_only=True)
    assert str(err.value) == (
        f"keyframe metadata {meta}: its keyframes' session '..' must be 1-64 characters of ASCII "
        "letters, digits or '_' (a robot id starts with a letter): it names folders, a ROS topic "
        "and pose-graph keys, e.g. 20261125T093000Z; the map was written before robot and "
        "session names were checked: rebuild it with valid names"
    )
    assert tree_digest(d) == before


def test_a_stored_row_named_against_the_rule_is_never_passed_on(tmp_path) -> None:
    """A format-3 row of robot 'x y' (its CRC32 right: written so by an older library user)."""
    from pair_vpr_ros.place_map.schema import COLUMNS, row_crc

    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        add_range(m, 0, 3)
        m.save(tmp_path / "map")
    conn = sqlite3.connect(tmp_path / "map" / "map-1.sqlite")
    row = conn.execute(f"SELECT {COLUMNS} FROM keyframes WHERE id = 1").fetchone()
    values = (*row[:11], "x y", *row[12:15])
    with conn:
        conn.execute(
            "UPDATE keyframes SET robot = 'x y', crc = ? WHERE id = 1", (row_crc(values),)
        )
    conn.close()
    with PlaceMap.load(tmp_path / "map", read_only=True) as m:
        assert m.meta(0).id == 0
        with pytest.raises(MapError) as err:
            m.meta(1)
    assert str(err.value) == (
        f"keyframe store {tmp_path / 'map' / 'map-1.sqlite'}: keyframe 1's robot 'x y' must be "
        "1-64 characters of ASCII letters, digits or '_' (a robot id starts with a letter): it "
        "names folders, a ROS topic and pose-graph keys, e.g. robot1; the map was written before "
        "robot and session names were checked: rebuild it with valid names"
    )
