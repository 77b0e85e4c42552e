"""Format 3 of a saved place map: maps of formats 1 and 2 (test/data/maps, written by the code
before issue 34) load with a note and are converted by the next save; saves are incremental; the
slow half of a save may run on another thread while keyframes are added."""

from __future__ import annotations

import json
import shutil
import sqlite3
import threading
from pathlib import Path

import numpy as np
import pytest
import test_place_map_persist as persist_tests
from test_bad_input_map import MAPS
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
    files,
    stored,
)  # fmt: skip

from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.dense_codec import BASIS_FROM

saved = persist_tests.saved  # fixture: a format-3 map of N0 keyframes in tmp_path / "map"


@pytest.mark.parametrize("version", [1, 2])
def test_an_old_map_loads_with_a_note_and_the_next_save_converts_it(tmp_path: Path, version):
    d = Path(shutil.copytree(MAPS / f"format-{version}", tmp_path / "map"))
    with PlaceMap.load(d, legacy_identity=("", "")) as m:  # v1: keyframes named at load
        assert_holds(m, list(range(N0)), "f16")  # float16 tokens, bit for bit
        assert f"is of format version {version}" in m.load_note
        assert "converted to format 4 by the next save into it" in m.load_note
        add_range(m, N0, N0 + 2)
        m.save(d)
        add_range(m, N0 + 2, N0 + 3)
        m.save(d)  # incremental from here
    manifest = json.loads((d / "manifest.json").read_text())
    assert (manifest["format_version"], manifest["dense_codec"]) == (4, "f16")
    assert files(d) == [
        "dense-1.f16",
        "manifest.json",
        "map-2.sqlite",
        "map-2.sqlite.desc",
        "map.lock",
    ]  # kept
    with PlaceMap.load(d, verify_dense=True) as m:
        assert_holds(m, list(range(N0 + 3)), "f16") and not m.load_note
        assert m.index_config.dense_codec == "f16"  # a loaded map keeps its own codec


def test_a_p4_map_of_its_first_encoder_decodes_as_then_and_continues(tmp_path: Path) -> None:
    """test/data/maps/format-3-p4: written by main at 631c860 (p4's components all on their full
    range); its tokens decode to the values that code gave, and later keyframes take the grids
    of today's encoder in the same layout."""
    d = Path(shutil.copytree(MAPS / "format-3-p4", tmp_path / "map"))
    then = np.load(MAPS / "format-3-p4.npy")  # [20, 4, 8] float16
    with PlaceMap.load(d, verify_dense=True) as m:
        assert (m.index_config.dense_codec, m.dense_basis.start) == ("p4", BASIS_FROM)
        assert len(m.dense_basis.recoded) == BASIS_FROM and not m.load_note
        np.testing.assert_array_equal(m.get_dense(range(20)), then)
        add_range(m, 20, 23)
        m.save(d)
    with PlaceMap.load(d, verify_dense=True) as m:
        np.testing.assert_array_equal(m.get_dense(range(20)), then)
        for i in range(20, 23):
            np.testing.assert_array_equal(
                m.get_dense([i])[0], stored(dense_for(i), "p4", m.dense_basis)
            )


def test_a_read_only_load_of_an_old_map_changes_nothing(tmp_path: Path) -> None:
    d = Path(shutil.copytree(MAPS / "format-2", tmp_path / "map"))
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    with PlaceMap.load(d, read_only=True) as m:
        assert_holds(m, list(range(N0)), "f16")
    assert {p.name: p.read_bytes() for p in d.iterdir()} == before


def test_an_incremental_save_writes_the_new_keyframes_only(saved: Path) -> None:
    """The store and the dense file grow by what was added; nothing is rewritten (but p4's head,
    written once when its basis is fitted at the 17th keyframe)."""
    store, dense = saved / "map-1.sqlite", saved / f"dense-1.{CODEC}"
    with PlaceMap.load(saved) as m:
        before = dense.read_bytes()
        add_range(m, N0, N0 + 40)
        m.save(saved)
        assert CODEC != "p4" or m.dense_basis is not None
    assert dense.read_bytes()[HEAD : len(before)] == before[HEAD:]
    assert dense.stat().st_size == HEAD + (N0 + 40) * ENTRY
    assert store.stat().st_size < 64 * 1024  # 52 small rows: no copy of anything
    with PlaceMap.load(saved) as m:
        assert_holds(m, list(range(N0 + 40)))


def test_flush_and_checkpoint_run_beside_adds(saved: Path) -> None:
    """As vpr_node saves: flush and checkpoint on another thread while the map thread adds."""
    with PlaceMap.load(saved) as m:
        lock, stop = threading.Lock(), threading.Event()

        def other_thread() -> None:
            while not stop.is_set():
                m.flush()
                m.checkpoint()

        side = threading.Thread(target=other_thread)
        side.start()
        for i in range(N0, N0 + 30):
            with lock:
                add_range(m, i, i + 1)
            if i % 10 == 0:
                m.save(saved, checkpoint=False)
        stop.set()
        side.join()
        m.save(saved)
    with PlaceMap.load(saved) as m:
        assert_holds(m, list(range(N0 + 30)))


def test_negative_zero_in_a_pose_survives_the_row_crc(tmp_path: Path) -> None:
    """SQLite gives -0.0 back as 0.0: the row CRC32 must not call that damage."""
    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        pose = (-0.0, 1.0, 2.0, -0.0, 0.0, 0.0, 1.0)
        m.add(desc_for(0), dense_for(0), KeyframeMeta(stamp=-0.0, pose=pose))
        m.save(tmp_path / "map")
    with PlaceMap.load(tmp_path / "map") as m:
        assert m.meta(0).pose == pose and m.all_meta()[0].stamp == 0.0


def _growth_rows(m: PlaceMap) -> None:
    """The growth rows of test/data/maps/format-3-growth (README): signatures, links, two
    represented keyframes; links without a score (none was kept before issue 48)."""
    from pair_vpr_ros.place_map.growth.tables import Represented

    for i in range(len(m)):
        m.growth.add_signature(i, np.linspace(0, 1, 96) * (i % 4) / 4)
    if len(m) == 12:
        m.growth.add_link(5, 1, (1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 1.0))
        m.growth.add_link(9, 5, (0.5, 0.0, 0.0, 0.0, 0.0, 0.08715574, 0.9961947))
        return
    m.growth.add_link(13, 9, (0.2, 0.1, 0.0, 0.0, 0.0, 0.0, 1.0))
    m.growth.add_link(17, 1, (0.3, 0.0, 0.1, 0.0, 0.0, 0.0, 1.0))
    m.growth.add_represented(Represented(250.0, "", "", 1, 0.01))
    m.growth.add_represented(Represented(251.0, "", "", 9, 0.02))


def _rows(m: PlaceMap) -> list:
    g = m.growth
    links = [g.scored_links(k) for k in range(len(m))]
    signatures = [g.signature(k) for k in range(len(m))]
    return [[None if s is None else s.tolist() for s in signatures], links, g.represented()]


def test_a_map_of_growth_rows_before_scores(tmp_path: Path) -> None:
    """test/data/maps/format-3-growth, written by main at 2b1c4db (schema version 0: links
    without a score column): read as written (its rows equal today's of the same calls, scores
    unknown); a read-only load changes nothing; a writable load migrates the store in its open
    transaction (schema.py), the next save commits it with format 4, and new links keep
    their score."""
    from pair_vpr_ros.place_map import schema

    with PlaceMap(DIM, SHAPE, "fp-a") as made:  # what the fixture's script did, today
        add_range(made, 0, 12)
        _growth_rows(made)
        add_range(made, 12, 20)
        _growth_rows(made)
        expected = _rows(made)
    d = Path(shutil.copytree(MAPS / "format-3-growth", tmp_path / "map"))
    version = "SELECT user_version FROM pragma_user_version"
    with PlaceMap.load(d, read_only=True) as m:
        assert _rows(m) == expected and m.growth.scored_links(9)[0][2] is None
    with sqlite3.connect(f"file:{d / 'map-1.sqlite'}?mode=ro", uri=True) as conn:
        assert conn.execute(version).fetchone() == (0,)
        assert not schema.has_column(conn, "links", "score")
    with PlaceMap.load(d) as m:
        assert _rows(m) == expected
        add_range(m, 20, 21)
        m.growth.add_link(20, 13, (0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), score=71.5)
        m.save(d)
    with sqlite3.connect(f"file:{d / 'map-1.sqlite'}?mode=ro", uri=True) as conn:
        assert conn.execute(version).fetchone() == (schema.SCHEMA_VERSION,)
    assert json.loads((d / "manifest.json").read_text())["format_version"] == 4
    with PlaceMap.load(d, read_only=True) as m:
        assert _rows(m)[1][:20] == expected[1][:13] + [
            links + ([(20, (-0.1, 0.0, 0.0, -0.0, -0.0, -0.0, 1.0), 71.5)] if k == 13 else [])
            for k, links in enumerate(expected[1][13:], 13)
        ]
        assert m.growth.scored_links(20) == [(13, (0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0), 71.5)]
