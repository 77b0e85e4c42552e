"""Bad-input matrix, the record of each completed save (issue 48): a keyframe store whose
write-ahead log was deleted, truncated, replaced by an older one or by another map's, or left
behind when the folder was copied, and a store of another map: a load, `pairvpr-map info` and
`merge` say what is missing and how to recover; `compact` (the way to go on) warns and keeps what
the store holds. A read-only or full --out of merge and compact is one error line, the inputs
unchanged. The write-ahead log stays about one save long while the map is open."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
from pathlib import Path

import pytest
from bad_input import tree_digest
from test_bad_input_map import MAPS
from test_place_map_persist import (
    DIM,
    N0,
    SHAPE,
    add_range,
    assert_holds,
    dense_for,
    desc_for,
    features_for,
    meta_for,
)

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.offline.map_cli import main
from pair_vpr_ros.place_map import PlaceMap, store

WAL = "map-1.sqlite-wal"


def _add(m: PlaceMap, start: int, stop: int, shift: int = 0) -> None:
    """Keyframes start..stop-1 with the content of keyframes start + shift.. (another map)."""
    for i in range(start + shift, stop + shift):
        m.add(desc_for(i), dense_for(i), meta_for(i), features_for(i))


def _open_map(d: Path, shift: int = 0) -> PlaceMap:
    """A map saved with N0 keyframes, then 2 more saved in place, its WAL not folded in (the
    node folds it on another thread, later): the store file alone holds N0. (At most 16
    keyframes in these maps: the 17th fits p4's basis, and the next save writes a new
    generation, dense_store.py.)"""
    m = PlaceMap(DIM, SHAPE, "fp-a")
    _add(m, 0, N0, shift)
    m.save(d)
    _add(m, N0, N0 + 2, shift)
    m.save(d, checkpoint=False)
    return m


def _copy(src: Path, dst: Path) -> Path:
    """The folder as a copy made while its map is open (without the writer's lock, -shm)."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("map.lock", "*-shm"))
    return dst


def _digest(d: Path) -> dict[str, str]:
    """The folder's files but SQLite's -shm (the index of its -wal, made by any reader)."""
    return {k: v for k, v in tree_digest(d).items() if not k.endswith("-shm")}


def _manifest(d: Path) -> dict:
    return json.loads((d / "manifest.json").read_text())


@pytest.fixture
def copies(tmp_path: Path) -> dict[str, Path]:
    """Copies of an open map folder, each damaged one way, and the store id of another map."""
    live, other = _open_map(tmp_path / "live"), _open_map(tmp_path / "other", shift=100)
    try:
        out = {name: _copy(tmp_path / "live", tmp_path / name)
               for name in ("deleted", "truncated", "foreign wal", "foreign store")}  # fmt: skip
        older = _copy(tmp_path / "live", tmp_path / "older")
        live.checkpoint()  # folded in: the next save's log starts afresh and holds it alone
        add_range(live, N0 + 2, N0 + 4)
        live.save(tmp_path / "live", checkpoint=False)
        out["older"] = _copy(tmp_path / "live", tmp_path / "newer")
        shutil.copy(older / WAL, out["older"] / WAL)  # the log of the save before the last
        shutil.copy(tmp_path / "other" / WAL, out["foreign wal"] / WAL)
        for name in ("map-1.sqlite", WAL):
            shutil.copy(tmp_path / "other" / name, out["foreign store"] / name)
    finally:
        live.close()
        other.close()
    (out["deleted"] / WAL).unlink()
    os.truncate(out["truncated"] / WAL, 32)  # its header only: every frame cut off
    (out["foreign store"] / "map-1.sqlite.desc").unlink()
    out["other id"] = _manifest(tmp_path / "other")["store_id"]
    return out


def _missing(d: Path, held: int, recorded: int, why: str) -> str:
    return (
        f"keyframe store {d / 'map-1.sqlite'} holds {held} keyframes, the last completed save "
        f"recorded {recorded} ({d / 'manifest.json'}): {recorded - held} keyframes ({held}.."
        f"{recorded - 1}) are missing; its write-ahead log {WAL} {why}: copy the map folder again "
        f"with its {WAL} (close the map first, or copy the folder whole), or restore it from a "
        f"backup; to go on with the {held} keyframes it holds: pairvpr-map compact {d} --out "
        "NEW_FOLDER"
    )


GONE = "is missing (deleted, or the folder was copied without it while the map was open)"
SHORT = "is truncated or older than that save"
CASES = {
    # name: (keyframes the store holds, the message's cause, or the whole message)
    "deleted": (N0, lambda d, c: _missing(d, N0, N0 + 2, GONE)),
    "truncated": (N0, lambda d, c: _missing(d, N0, N0 + 2, SHORT)),
    "older": (N0 + 2, lambda d, c: _missing(d, N0 + 2, N0 + 4, SHORT)),
    # another map's log over this store's pages: read as damage, the file alone is this map's
    "foreign wal": (
        None,
        lambda d, c: (
            f"keyframe store {d / 'map-1.sqlite'}: its write-ahead log {WAL} belongs to another "
            "map (its pages do not fit this store; the store's own file is this map's): the "
            f"map's own log was replaced; move {WAL} away and load the map again (it then holds "
            "the keyframes its file holds), or restore the map folder from a backup"
        ),
    ),
    "foreign store": (
        None,
        lambda d, c: (
            f"keyframe store {d / 'map-1.sqlite'} belongs to another map (store {c['other id']!r}"
            f"; {d / 'manifest.json'} names {_manifest(d)['store_id']!r}): it was replaced by "
            "another map's; restore the map folder from a backup, or load the map it belongs to"
        ),
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_a_store_that_lost_saved_keyframes_is_named_by_every_reader(copies, tmp_path, case):
    """Finding 1 and 2: load, info and merge refuse with the same message (nothing changed);
    compact, the way to go on, keeps what the store holds with the message as a warning."""
    d, (held, message) = copies[case], CASES[case]
    text = message(d, copies)
    before = _digest(d)
    for read_only in (False, True):
        with pytest.raises(MapError) as err:
            PlaceMap.load(d, read_only=read_only)
        assert str(err.value) == text
    assert main(["info", str(d)]) == 1
    assert main(["merge", str(d), str(tmp_path / "other"), "--out", str(tmp_path / "m")]) == 1
    assert _digest(d) == before and not (tmp_path / "m").exists()
    if held is None:
        return
    assert main(["compact", str(d), "--out", str(tmp_path / "c"), "--no-policy"]) == 0
    with PlaceMap.load(tmp_path / "c", read_only=True) as m:
        assert_holds(m, list(range(held)))


def test_the_messages_reach_the_command_line(copies, tmp_path, capsys) -> None:
    d = copies["deleted"]
    text = _missing(d, N0, N0 + 2, GONE)
    assert main(["info", str(d)]) == 1
    assert capsys.readouterr().err == f"error: {text}\n"
    assert main(["merge", str(d), str(copies["older"]), "--out", str(tmp_path / "m")]) == 1
    assert capsys.readouterr().err == f"error: input map {d} cannot be merged: {text}\n"
    assert main(["compact", str(d), "--out", str(tmp_path / "c")]) == 0
    err = capsys.readouterr().err
    assert err.startswith(f"warning: {text.split(': copy the map folder')[0]}\n")


def test_a_map_opened_writable_with_missing_ok_records_what_it_holds(copies) -> None:
    d = copies["deleted"]
    with PlaceMap.load(d, missing_ok=True) as m:
        assert len(m) == N0 and m.load_note == _missing(d, N0, N0 + 2, GONE).split(": copy")[0]
        m.save(d)
    assert _manifest(d)["count"] == N0
    with PlaceMap.load(d) as m:
        assert_holds(m, list(range(N0)))


def test_a_map_of_format_3_is_checked_against_its_first_save(tmp_path) -> None:
    """A format-3 manifest counts the keyframes of its generation's first save: a store with
    fewer is found too; one with more (its later saves) loads, and its next save records."""
    d = Path(shutil.copytree(MAPS / "format-3-growth", tmp_path / "m"))
    with PlaceMap.load(d) as m:
        assert len(m) == 20
        m.save(d)
    assert (_manifest(d)["format_version"], _manifest(d)["count"]) == (4, 20)
    conn = sqlite3.connect(d / "map-1.sqlite")
    with conn:
        conn.execute("DELETE FROM keyframes WHERE id >= 15")
        conn.execute("DELETE FROM features WHERE id >= 15")
    conn.close()
    (d / "map-1.sqlite.desc").unlink()
    with pytest.raises(MapError, match=r"holds 15 keyframes, the last completed save recorded 20"):
        PlaceMap.load(d, read_only=True)


# ---- finding 3: the WAL is started afresh after each checkpoint, also when it ran late


@pytest.mark.parametrize("late", [False, True])
def test_the_write_ahead_log_stays_about_one_save_long(tmp_path: Path, late: bool) -> None:
    """Saves of 3 keyframes, folded in by `checkpoint` after the save (the node's way: on
    another thread, `late`: after the next keyframe came) or by the save itself: the -wal stays
    within a few saves' worth (before issue 48 it kept every save: 20 saves 7x the first's)."""
    sizes = []
    with PlaceMap(DIM, SHAPE, "fp-a", work_dir=tmp_path) as m:
        add_range(m, 0, 20)
        m.save(tmp_path / "map")
        for _ in range(20):
            add_range(m, len(m), len(m) + 3)
            m.save(tmp_path / "map", checkpoint=not late)
            if late:
                add_range(m, len(m), len(m) + 1)
                m.checkpoint()
            sizes.append((tmp_path / "map" / WAL).stat().st_size)
    assert max(sizes[10:]) <= 3 * max(sizes[:3])
    assert not (tmp_path / "map" / WAL).exists()  # closing folds it in and removes it


# ---- findings 4 and 5: --out read-only or its disk full: one error line, nothing left


@pytest.mark.parametrize("command", ["merge", "compact"])
def test_a_read_only_out_is_refused_before_the_work(tmp_path, capsys, command) -> None:
    a = _copy_closed(tmp_path)
    args = [str(a), str(a.parent / "b")] if command == "merge" else [str(a)]
    before = tree_digest(tmp_path)
    assert main([command, *args, "--out", "/proc/out"]) == 1
    assert capsys.readouterr().err == (
        "error: cannot write --out /proc/out: /proc is not writable (No such file or "
        "directory); pick a writable folder\n"
    )
    assert tree_digest(tmp_path) == before


def _copy_closed(tmp_path: Path) -> Path:
    """Maps a and b of 6 keyframes, each with 3000 bytes of features (about a store page)."""
    for name, start in (("a", 0), ("b", 50)):
        with PlaceMap(DIM, SHAPE, "fp-a") as m:
            for i in range(start, start + 6):
                m.add(desc_for(i), dense_for(i), meta_for(i), bytes(range(256)) * 12)
            m.save(tmp_path / name)
    return tmp_path / "a"


@pytest.mark.parametrize("command", ["merge", "compact"])
@pytest.mark.parametrize("pages", [1, 12])  # at the store's first table / at its 3rd keyframe
def test_a_full_disk_at_out_says_so(tmp_path, capsys, monkeypatch, command, pages) -> None:
    """SQLite's own SQLITE_FULL (its page limit stands in for the disk's end) in the new map
    beside --out: named as a full disk, never as a damaged map, with the tool's own advice."""
    a = _copy_closed(tmp_path)
    connect = sqlite3.connect

    def limited(path, *args, **kwargs):
        conn = connect(path, *args, **kwargs)
        if ".merging-" in str(path):
            conn.execute(f"PRAGMA max_page_count = {pages}")
        return conn

    monkeypatch.setattr(store.sqlite3, "connect", limited)
    args = [str(a), str(a.parent / "b"), "--quiet"] if command == "merge" else [str(a)]
    before = tree_digest(tmp_path)
    assert main([command, *args, "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    what = "merging" if command == "merge" else "compacting"
    assert err.startswith(
        f"error: {what} into --out {tmp_path / 'out'} failed: the disk is full (database or disk "
        f"is full), writing in {tmp_path}/.out.merging-"
    )
    assert err.endswith(
        "; nothing was written to --out and the inputs are unchanged: free disk space in "
        f"{tmp_path} (or pick another --out) and run it again\n"
    )
    assert tree_digest(tmp_path) == before  # no --out, no work folder


def test_a_full_tmpdir_under_a_new_map_says_so(tmp_path, monkeypatch) -> None:
    """Finding 5 for the node and the replay: a never-saved map works in $TMPDIR (or work_dir);
    there a full disk reads as one, at its folder or at its keyframe store."""
    import errno
    import tempfile

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as mp:
        mp.setattr(tempfile, "mkdtemp", full)
        with pytest.raises(MapError) as err:
            PlaceMap(DIM, SHAPE, "fp-a")
    assert str(err.value) == (
        f"cannot create a working folder in {tempfile.gettempdir()}: the disk is full (No space "
        "left on device)"
    )
    connect = sqlite3.connect

    def limited(path, *args, **kwargs):
        conn = connect(path, *args, **kwargs)
        conn.execute("PRAGMA max_page_count = 1")
        return conn

    monkeypatch.setattr(store.sqlite3, "connect", limited)
    with pytest.raises(MapError) as err:
        PlaceMap(DIM, SHAPE, "fp-a", work_dir=tmp_path)
    (work,) = tmp_path.iterdir()
    assert str(err.value) == (
        f"keyframe store {work / 'store-work-1.sqlite'} cannot be opened: the disk is full "
        "(database or disk is full): free disk space there (SQLite also writes temporary files "
        "to $TMPDIR) and retry"
    )
