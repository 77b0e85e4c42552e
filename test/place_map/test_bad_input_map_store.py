"""Bad-input matrix, map folders of format 3: a damaged manifest, keyframe store or dense file, a
foreign or truncated segment, a flipped byte anywhere, a full disk during a save, two processes
writing one map: each a MapError naming the file (or a byte nobody uses), the last save kept."""

from __future__ import annotations

import errno
import json
import os
import shutil
import sqlite3
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path
from zlib import crc32

import faiss
import numpy as np
import pytest
import test_place_map_persist as persist_tests
from bad_input import saved_map_digest, tree_digest
from test_place_map_persist import (
    CODEC,
    DIM,
    ENTRY,
    HEAD,
    N0,
    SHAPE,
    add_range,
    assert_holds,
    dense_for,
    desc_for,
    flip_byte,
    meta_for,
)  # fmt: skip

from pair_vpr_ros.errors import MapError, MapFingerprintError
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.place_map import (
    IndexConfig,
    KeyframeMeta,
    PlaceMap,
    dense_store,
    files,
    manifest,
    persist,
)
from pair_vpr_ros.place_map.files import LOCK_NAME
from pair_vpr_ros.place_map.store import KeyframeStore

saved = persist_tests.saved  # fixture: a format-3 map of N0 keyframes in tmp_path / "map"
DENSE = f"dense-1.{CODEC}"  # the default codec's file; p4: a head for the basis (zeros: N0 < 16)


def _edit_manifest(d: Path, edit) -> None:
    data = json.loads((d / "manifest.json").read_text())
    edit(data)
    (d / "manifest.json").write_text(json.dumps(data))


def resign_manifest(d: Path, edit) -> None:
    """Edit the manifest and fix its CRC32 (as if it was written that way), for deeper checks."""
    data = json.loads((d / "manifest.json").read_text())
    edit(data)
    m = manifest.Manifest(**data)
    m.checksum = m.content_crc()
    (d / "manifest.json").write_text(json.dumps(asdict(m)))


def replace_snapshot(d: Path, content: bytes) -> None:
    """Overwrite the index snapshot the store names and fix its CRC32 there."""
    conn = sqlite3.connect(d / "map-1.sqlite")
    (name,) = conn.execute("SELECT value FROM state WHERE key = 'index_file'").fetchone()
    (d / name).write_bytes(content)
    with conn:
        conn.execute("UPDATE state SET value = ? WHERE key = 'index_crc'", (str(crc32(content)),))
    conn.close()


def faiss_snapshot(d: Path, index) -> None:
    tmp = d.parent / "other.faiss"
    faiss.write_index(index, str(tmp))
    replace_snapshot(d, tmp.read_bytes())


def _sql(d: Path, *statements: str, cache: bool = True) -> None:
    if not cache:  # without the descriptor cache a load reads (and checks) every row
        (d / "map-1.sqlite.desc").unlink()
    conn = sqlite3.connect(d / "map-1.sqlite")
    with conn:
        for sql in statements:
            conn.execute(sql)
    conn.close()


def _foreign_store(d: Path) -> None:
    (d / "map-1.sqlite").unlink()
    _sql(d, "PRAGMA journal_mode=WAL", "CREATE TABLE notes (t TEXT)")


def _foreign_dense(d: Path) -> None:
    """The dense file of another map of the same model and shape."""
    with PlaceMap(DIM, SHAPE, "fp-a") as other:
        for i in range(N0):
            other.add(desc_for(i), dense_for(i + 100), meta_for(i))
        other.save(d.parent / "other")
    os.replace(d.parent / "other" / DENSE, d / DENSE)


CORRUPTIONS = {
    "manifest byte changed": (
        lambda d: _edit_manifest(d, lambda m: m.update(fingerprint="fp-b")),
        r"manifest.json fails its CRC32 check \(a changed or damaged byte\)",
    ),
    "manifest without checksum": (
        lambda d: _edit_manifest(d, lambda m: m.pop("checksum")),
        r"manifest.json fails its CRC32 check",
    ),
    "manifest codec": (
        lambda d: _edit_manifest(d, lambda m: m.update(dense_codec="q2")),
        r"has missing or invalid fields \(unknown dense_codec 'q2'\)",
    ),
    "missing store": (
        lambda d: (d / "map-1.sqlite").unlink(),
        r"map file .*map-1.sqlite listed in .*manifest.json is missing",
    ),
    "missing dense": (
        lambda d: (d / DENSE).unlink(),
        rf"map file .*{DENSE} listed in .*manifest.json is missing",
    ),
    "store garbage": (
        lambda d: (d / "map-1.sqlite").write_bytes(b"not a database" * 100),
        r"keyframe store .*map-1.sqlite is not a readable SQLite database \(file is not a "
        r"database\): the map is damaged",
    ),
    "store truncated": (
        lambda d: os.truncate(d / "map-1.sqlite", 4096),
        r"keyframe store .*map-1.sqlite is not a readable SQLite database \(database disk image "
        r"is malformed\)",
    ),
    "foreign store": (
        _foreign_store,
        r"keyframe store .*map-1.sqlite cannot be read \(no such table: keyframes\)",
    ),
    "descriptor changed": (  # without the descriptor cache: see the tests of the cache below
        lambda d: _sql(d, "UPDATE keyframes SET descriptor = zeroblob(32) WHERE id = 3", cache=0),
        r"map-1.sqlite holds keyframe 3 with a wrong CRC32 \(a damaged row\)",
    ),
    "row missing": (
        lambda d: _sql(d, "DELETE FROM keyframes WHERE id = 5", cache=0),
        r"map-1.sqlite holds 11 keyframe rows with ids 0..11: rows are missing",
    ),
    "stray feature row": (
        lambda d: _sql(d, "INSERT INTO features (id, crc, data) VALUES (99, 0, x'00')"),
        r"map-1.sqlite holds 1 feature rows of no keyframe",
    ),
    "foreign dense segment": (
        _foreign_dense,
        rf"{DENSE} does not match its manifest: keyframe 0 fails its CRC32 check when read "
        rf"as \[4, 8\] {CODEC} tokens",
    ),
    "truncated dense segment": (
        lambda d: os.truncate(d / DENSE, HEAD + 11 * ENTRY + 5),
        rf"dense token file .*{DENSE} is too short: {HEAD + 11 * ENTRY + 5} bytes hold 11 "
        r"keyframes, the manifest lists 12",
    ),
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


def test_a_changed_keyframe_row_is_a_map_error_when_read(saved: Path) -> None:
    """Rows are checked when read (a load reads only descriptors and dense CRC32s)."""
    _sql(saved, "UPDATE keyframes SET stamp = stamp + 1 WHERE id = 3")
    with PlaceMap.load(saved) as m:
        assert m.meta(2) == meta_for(2).__class__(2, *list(meta_for(2).__dict__.values())[1:])
        with pytest.raises(MapError, match=r"holds keyframe 3 with a wrong CRC32 \(a damaged"):
            m.meta(3)
        with pytest.raises(MapError, match=r"holds keyframe 3 with a wrong CRC32"):
            m.all_meta()


def _outcome(d: Path) -> str:
    """'error': a MapError at load or on a read; 'same': every value as saved (an unused byte)."""
    try:
        with PlaceMap.load(d, read_only=True) as m:
            assert_holds(m, list(range(N0)))
            m.all_meta()
    except MapError:
        return "error"
    return "same"


@pytest.mark.slow  # 144 copies of a map loaded and read
@pytest.mark.parametrize("name", ["map-1.sqlite", DENSE, "manifest.json"])
def test_a_flipped_byte_anywhere_is_reported_never_used(saved: Path, tmp_path: Path, name: str):
    size = (saved / name).stat().st_size
    offsets = np.unique(np.linspace(0, size - 1, 48).astype(int))
    errors = 0
    for offset in offsets:
        copy = tmp_path / f"flip-{offset}"
        shutil.copytree(saved, copy)
        flip_byte(copy / name, int(offset))
        errors += _outcome(copy) == "error"  # an AssertionError (a wrong value) fails the test
    # Every dense and manifest byte is used but p4's head before its basis is fitted (zeros,
    # overwritten by the fit); SQLite pages have free space and slack, so a few of the sampled
    # flips in the store change nothing a load or query reads.
    used = np.count_nonzero(offsets >= (HEAD if name == DENSE else 0))
    assert errors >= (used if name != "map-1.sqlite" else 4)


def test_a_missing_index_snapshot_is_a_map_error(tmp_path: Path) -> None:
    with PlaceMap(DIM, SHAPE, "fp-a", IndexConfig(kind="hnsw")) as m:
        add_range(m, 0, 3)
        m.save(tmp_path / "map")
    (snapshot,) = (tmp_path / "map").glob("index-1-*.faiss")
    snapshot.unlink()
    with pytest.raises(MapError, match=rf"the index snapshot '{snapshot.name}' that .* names is"):
        PlaceMap.load(tmp_path / "map")


def test_a_changed_index_snapshot_fails_its_crc(tmp_path: Path) -> None:
    with PlaceMap(DIM, SHAPE, "fp-a", IndexConfig(kind="hnsw")) as m:
        add_range(m, 0, 3)
        m.save(tmp_path / "map")
    (snapshot,) = (tmp_path / "map").glob("index-1-*.faiss")
    flip_byte(snapshot, 50)
    with pytest.raises(MapError, match=rf"index snapshot .*{snapshot.name} fails its CRC32 check"):
        PlaceMap.load(tmp_path / "map")


def test_unsaved_tail_is_kept_not_truncated(saved: Path) -> None:
    """A dense file longer than the saved rows (a session that never saved) is never shrunk."""
    with PlaceMap.load(saved) as m:
        add_range(m, N0, N0 + 3)  # appended, never saved
    size = (saved / DENSE).stat().st_size
    assert size == HEAD + (N0 + 3) * ENTRY
    with PlaceMap.load(saved) as m:
        assert (saved / DENSE).stat().st_size == size
        assert_holds(m, list(range(N0)))
        add_range(m, N0, N0 + 1)  # overwrites the first tail entry
        m.save(saved)
    with PlaceMap.load(saved, verify_dense=True) as m:
        assert_holds(m, list(range(N0 + 1)))


HOLDER = """
import sys, time
from pair_vpr_ros.place_map import PlaceMap
m = PlaceMap.load(sys.argv[1])
print("ready", flush=True)
time.sleep(60)
"""


def test_two_processes_cannot_write_one_map(saved: Path) -> None:
    child = subprocess.Popen(
        [sys.executable, "-c", HOLDER, str(saved)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout.readline().strip() == "ready"
        with pytest.raises(MapError) as err:
            PlaceMap.load(saved)
        assert str(err.value) == (
            f"map directory {saved} is open for writing by another PlaceMap (pid {child.pid}); "
            "close that one first, or load this map with read_only=True"
        )
        with PlaceMap.load(saved, read_only=True) as reader:  # readers may share it
            assert_holds(reader, list(range(N0)))
        # Past the lock (a folder whose lock file was replaced): SQLite's own write lock.
        with pytest.raises(MapError, match=r"map-1.sqlite is being written by another process"):
            KeyframeStore(saved / "map-1.sqlite", saved=True)
    finally:
        child.kill()
        child.wait()


def _model_map(tiny_model, tmp_path: Path, count: int = 3) -> Path:
    pipe = LoopClosurePipeline(tiny_model)
    n, d = tiny_model.num_patches, tiny_model.config.embed_dim
    rng = np.random.default_rng(0)
    for i in range(count):
        pipe.place_map.add(rng.normal(size=512), rng.normal(size=(n, d)), KeyframeMeta(stamp=i))
    path = pipe.save_map(tmp_path / "map")
    pipe.close()
    return path


@pytest.mark.parametrize("case", ["descriptor changed", "store garbage", "manifest byte changed"])
def test_pipeline_load_map_gives_map_error_and_keeps_its_map(tiny_model, tmp_path, case) -> None:
    path = _model_map(tiny_model, tmp_path, count=6)
    damage, message = CORRUPTIONS[case]
    damage(path)
    before = tree_digest(path)
    pipe = LoopClosurePipeline(tiny_model)
    pipe.place_map.add(
        np.ones(512), np.ones((tiny_model.num_patches, 32)), KeyframeMeta(stamp=0.0)
    )
    with pytest.raises(MapError, match=message):
        pipe.load_map(path)
    assert len(pipe.place_map) == 1  # the map it had is still there
    pipe.close()
    assert tree_digest(path) == before


def test_pipeline_refuses_a_map_of_other_shapes(tiny_model, tmp_path) -> None:
    path = _model_map(tiny_model, tmp_path, count=0)
    with PlaceMap.load(path) as m:  # a map of another shape, with a valid manifest
        other = PlaceMap(m.desc_dim, (16, 8), m.fingerprint)
    other.save(tmp_path / "other")
    other.close()
    pipe = LoopClosurePipeline(tiny_model)
    with pytest.raises(MapFingerprintError, match=r"dense tokens of \[16, 8\], this model makes"):
        pipe.load_map(tmp_path / "other")
    assert len(pipe.place_map) == 0
    pipe.close()
    PlaceMap.load(tmp_path / "other").close()  # the refused map was closed (its lock released)


# ---- a full disk during a save: the last save kept, nothing left behind, the save retried


def _enospc(*_args, **_kw):
    raise OSError(errno.ENOSPC, "No space left on device")


def _partial_then_enospc(path, *_args, **_kw):
    Path(path).write_bytes(b"\0" * 100)  # what a full disk leaves: a partial file
    _enospc()


def _copy_then_enospc(_src_fd, dst, _nbytes):
    _partial_then_enospc(dst)


def _commit_full(rollback: bool):
    def setup(m: PlaceMap, mp) -> None:
        def full() -> None:
            if rollback:  # what SQLite may do with a transaction that hit a full disk
                m._store._conn.execute("ROLLBACK")
            raise sqlite3.OperationalError("database or disk is full")

        mp.setattr(m._store, "_commit_sql", full)

    return setup


FULL_DISK_AT = {
    "dense copy": lambda m, mp: mp.setattr(dense_store, "copy_prefix", _copy_then_enospc),
    "store": lambda m, mp: mp.setattr(
        KeyframeStore, "copy_to", lambda _self, path, _state, _crcs: _partial_then_enospc(path)
    ),
    "manifest": lambda m, mp: mp.setattr(manifest, "write_bytes_durably", _partial_then_enospc),
    "fsync": lambda m, mp: mp.setattr(persist, "fsync_path", _enospc),
    "dense sync": lambda m, mp: mp.setattr(m._dense, "sync", _enospc),
    "commit": _commit_full(rollback=False),
    "commit rolled back": _commit_full(rollback=True),
}
FULL_DISK_CASES = [("save_as", "dense copy")] + [
    (mode, step) for mode in ("save_as", "fresh") for step in ("store", "manifest", "fsync")
] + [("append", step) for step in ("dense sync", "commit", "commit rolled back")]  # fmt: skip


@pytest.mark.parametrize(("mode", "step"), FULL_DISK_CASES)
def test_full_disk_save_leaves_nothing_behind(saved, tmp_path, monkeypatch, mode, step) -> None:
    target = tmp_path / "other" if mode == "save_as" else saved
    m = PlaceMap(DIM, SHAPE, "fp-a") if mode == "fresh" else PlaceMap.load(saved)
    start = len(m)
    add_range(m, start, start + 2)
    listing = sorted(os.listdir(target)) if target.exists() else None  # a new folder
    before = saved_map_digest(saved)
    with monkeypatch.context() as mp:
        FULL_DISK_AT[step](m, mp)
        message = r"saving the place map to .* failed .*(No space left|disk is full)"
        if step == "commit rolled back":
            message += r".*the 2 keyframes added since the last save are dropped, the map "
            message += r"continues from the last save \(12 keyframes\): free disk space"
        with pytest.raises(MapError, match=message):
            m.save(target)
    assert saved_map_digest(saved) == before
    live = m._dense.path.name if m._dense.path.parent == target else None  # moved, not copied
    if listing is None:  # issue 25: a failed save into a folder it made leaves no folder
        assert not target.exists()
    else:
        assert sorted(n for n in os.listdir(target) if n != live) == [
            n for n in listing if n != live
        ]
    kept = start if step == "commit rolled back" else start + 2
    assert len(m) == kept
    m.save(target)  # and the save can be retried
    m.close()
    with PlaceMap.load(target) as again:
        assert_holds(again, list(range(kept)))


def test_full_disk_at_the_lock_file_is_a_map_error_and_leaves_no_folder(tmp_path, monkeypatch):
    target = tmp_path / "new" / "map"
    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        add_range(m, 0, 2)
        with monkeypatch.context() as mp:
            mp.setattr(files.os, "pwrite", _enospc)
            with pytest.raises(MapError) as err:
                m.save(target)
        assert str(err.value) == (
            f"cannot write the lock file {target / LOCK_NAME} (No space left on device): free "
            "disk space or pick another directory and retry"
        )
        assert not target.exists() and (tmp_path / "new").is_dir()
        m.save(target)  # retried once there is room
    with PlaceMap.load(target) as again:
        assert_holds(again, [0, 1])


def test_save_over_another_models_map_is_refused_unless_overwrite(saved) -> None:
    before = saved_map_digest(saved)
    with PlaceMap(DIM, SHAPE, "fp-b") as other:
        add_range(other, 0, 1)
        with pytest.raises(MapFingerprintError) as err:
            other.save(saved)
        assert str(err.value) == (
            f"map directory {saved} holds a map of another model (fingerprint 'fp-a', this "
            "map's is 'fp-b'): save into another directory, or pass overwrite=True to replace it"
        )
        assert saved_map_digest(saved) == before
        other.save(saved, overwrite=True)
    with PlaceMap.load(saved) as again:
        assert again.fingerprint == "fp-b" and len(again) == 1


def test_save_over_the_same_models_map_still_replaces_it(saved) -> None:
    with PlaceMap(DIM, SHAPE, "fp-a") as same:
        add_range(same, 0, 1)
        same.save(saved)
    with PlaceMap.load(saved) as again:
        assert len(again) == 1
