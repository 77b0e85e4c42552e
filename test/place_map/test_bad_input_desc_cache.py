"""Bad-input matrix, the descriptor cache of a flat map (`map-<g>.sqlite.desc`, derived from the
keyframe store): a damaged, short, foreign or missing cache is never used (the load, or the
first search when only the CRC32 check of its rows fails, reads the checked rows instead, with
the same results) and the next save writes it again; a damaged keyframe row behind a valid
cache is still reported when the row is read."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import test_place_map_persist as persist_tests
from test_place_map_persist import N0, add_range, assert_holds, desc_for, flip_byte

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map import PlaceMap

saved = persist_tests.saved  # fixture: a format-3 map of N0 keyframes in tmp_path / "map"
CACHE = "map-1.sqlite.desc"
ROW = 4 * 8  # a [8] float32 descriptor


def hits(m: PlaceMap) -> list:
    return [m.search(desc_for(i), 3) for i in range(N0)]


def uses_cache(m: PlaceMap) -> bool:
    """The map searches its descriptor cache (the first search waits for its CRC32 check)."""
    m.search(desc_for(0), 1)
    return m._desc_cache is not None and not m._index.cache_failed


DAMAGES = {
    "a flipped descriptor byte": lambda p: flip_byte(p, 4096 + 5 * ROW + 2),
    "a flipped header byte": lambda p: flip_byte(p, 13),
    "truncated": lambda p: os.truncate(p, 4096 + 11 * ROW),
    "garbage": lambda p: p.write_bytes(b"not a cache" * 999),
    "empty": lambda p: p.write_bytes(b""),
    "missing": lambda p: p.unlink(),
}


@pytest.mark.parametrize("case", DAMAGES)
def test_a_bad_cache_is_not_used_and_the_next_save_writes_it_again(saved: Path, case) -> None:
    with PlaceMap.load(saved, read_only=True) as m:
        assert uses_cache(m)
        want = hits(m)
    DAMAGES[case](saved / CACHE)
    with PlaceMap.load(saved, read_only=True) as m:
        assert not uses_cache(m) and hits(m) == want  # the rows, each checked
    with PlaceMap.load(saved) as m:
        add_range(m, N0, N0 + 2)
        m.save(saved)
    with PlaceMap.load(saved, read_only=True) as m:
        assert uses_cache(m)
        assert_holds(m, list(range(N0 + 2)))


def test_a_cache_of_another_count_is_not_used(saved: Path, tmp_path: Path) -> None:
    with PlaceMap.load(saved) as m:
        add_range(m, N0, N0 + 3)
        m.save(saved)
    older = (saved / CACHE).read_bytes()
    with PlaceMap.load(saved) as m:
        add_range(m, N0 + 3, N0 + 4)
        m.save(saved)
    (saved / CACHE).write_bytes(older)  # N0 + 3 rows: one short of the store
    with PlaceMap.load(saved, read_only=True) as m:
        assert not uses_cache(m)
        assert_holds(m, list(range(N0 + 4)))


def test_a_loaded_map_grows_and_its_cache_with_it(saved: Path) -> None:
    before = (saved / CACHE).stat().st_size
    with PlaceMap.load(saved) as m:
        add_range(m, N0, N0 + 5)  # the first add copies the viewed descriptors
        m.save(saved)
    assert (saved / CACHE).stat().st_size == before + 5 * ROW
    with PlaceMap.load(saved, read_only=True) as m:
        assert uses_cache(m)
        assert_holds(m, list(range(N0 + 5)))


def _sql(d: Path, sql: str) -> None:
    conn = sqlite3.connect(d / "map-1.sqlite")
    with conn:
        conn.execute(sql)
    conn.close()


def test_a_damaged_row_behind_a_valid_cache_is_reported_when_read(saved: Path) -> None:
    _sql(saved, "UPDATE keyframes SET descriptor = zeroblob(32) WHERE id = 3")
    with PlaceMap.load(saved, read_only=True) as m:
        assert uses_cache(m) and m.search(desc_for(3), 1)[0][0] == 3  # the checked cache
        m.meta(2)
        with pytest.raises(MapError, match=r"holds keyframe 3 with a wrong CRC32 \(a damaged"):
            m.meta(3)


def test_a_missing_row_behind_a_valid_cache_is_reported_when_read(saved: Path) -> None:
    _sql(saved, "DELETE FROM keyframes WHERE id = 5")
    with PlaceMap.load(saved, read_only=True) as m:
        with pytest.raises(MapError, match=r"has no row for keyframe 5 \(rows are missing\)"):
            m.meta(5)
        with pytest.raises(MapError, match="has no dense CRC32 for keyframe 5"):
            m.get_dense([5])
        assert np.isfinite(m.get_dense([4])).all()
