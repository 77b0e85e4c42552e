"""Index kind "milvus" on milvus-lite and a Milvus server (milvus_fixtures.py): same answers as
the exact FAISS index, filters instead of over-fetching, save/load re-attach, faults (a server
that goes away), several writers."""

from __future__ import annotations

import logging
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from bad_input import make_flaky
from exact_match import EXACT_MATCH
from test_place_map_persist import DIM, SHAPE, add_range, dense_for, desc_for, meta_for

from pair_vpr_ros.errors import MapError, MapUnavailableError
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.recency import eligible_keyframes
from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.milvus.expr import (
    Exclusion,
    IdentityRuns,
    exclusion_expr,
    ids_expr,
    mask_runs,
)

N = 40


def filled(config: IndexConfig, n: int = N, fingerprint: str = "fp") -> PlaceMap:
    m = PlaceMap(DIM, SHAPE, fingerprint, index=config)
    add_range(m, 0, n)
    return m


def test_an_inserted_keyframe_is_found_by_the_next_query(milvus):
    with PlaceMap(DIM, SHAPE, "fp", index=milvus) as m:
        for i in range(5):
            assert m.add(desc_for(i), dense_for(i), meta_for(i)) == i
            top = m.search(desc_for(i), 1)  # Strong consistency: no wait, no flush
            assert top[0][0] == i and top[0][1] == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("level", ["Bounded", "Session", "Strong"])
def test_answers_equal_the_exact_faiss_index(milvus, level):
    rng = np.random.default_rng(3)
    allowed = rng.random(N) < 0.5
    milvus = replace(milvus, milvus_consistency=level)
    with filled(milvus) as m, filled(IndexConfig(kind="flat")) as flat:
        for q in range(0, N, 7):
            for kwargs in ({}, {"max_id": 17}, {"allowed": allowed}, {"max_id": 0}):
                got, want = (
                    m.search(desc_for(q), 5, **kwargs),
                    flat.search(desc_for(q), 5, **kwargs),
                )
                assert [i for i, _ in got] == [i for i, _ in want], kwargs
                np.testing.assert_allclose([s for _, s in got], [s for _, s in want], atol=1e-5)
        assert m.search(desc_for(0), 5, allowed=np.zeros(N, bool)) == []
        np.testing.assert_array_equal(m.get_desc([3, 1]), flat.get_desc([3, 1]))


def test_temporal_exclusion_is_a_filter_equal_to_the_stamp_mask(milvus):
    """Stamps out of order (a replayed bag): the filter lets through exactly the keyframes
    `eligible_keyframes` allows, and k results come back however many recent frames are closer."""
    stamps = np.random.default_rng(5).permutation(N).astype(float) * 2.0
    with PlaceMap(DIM, SHAPE, "fp", index=milvus) as m, PlaceMap(DIM, SHAPE, "fp") as flat:
        for i, t in enumerate(stamps):
            for mp in (m, flat):
                mp.add(desc_for(i), dense_for(i), KeyframeMeta(stamp=t))
        for q, window, recent in ((30, 10.0, 3), (7, 0.0, 0), (12, 25.0, 8)):
            mask = eligible_keyframes(stamps, stamps[q], window, recent)
            rule = Exclusion(stamps[q], window, N - recent, "robot", m.session)
            got = m.search(desc_for(q), 6, exclusion=rule)
            want = flat.search(desc_for(q), 6, allowed=mask)
            assert [i for i, _ in got] == [i for i, _ in want] and len(got) == 6


def test_other_robots_and_sessions_are_candidates_at_once(milvus):
    """Issue 22: temporal exclusion applies within the query's robot and session only."""
    with PlaceMap(DIM, SHAPE, "fp", index=milvus) as m:
        index = m._index
        rows = [("a", "s1", 10.0), ("b", "s1", 10.0), ("a", "s2", 10.0), ("a", "s1", 500.0)]
        for i, row in enumerate(rows):
            index.add(desc_for(i)[None], [row])
        found = index.search(desc_for(0), 10, exclusion=Exclusion(10.0, 30.0, 4, "a", "s1"))[0]
        assert sorted(found.tolist()) == [1, 2, 3]
        found = index.search(desc_for(0), 10, exclusion=Exclusion(10.0, 30.0, 3, "a", "s1"))[0]
        assert sorted(found.tolist()) == [1, 2]  # 3: among the newest of its robot and session
        found = index.search(desc_for(0), 10, exclusion=Exclusion(10.0, 0.0, 4, "a", "s1"))[0]
        assert sorted(found.tolist()) == [1, 2, 3]  # 0: at the query's very stamp


def test_filter_expressions():
    assert mask_runs(np.array([1, 1, 0, 0, 1, 0, 1], bool)) == [(0, 2), (4, 5), (6, 7)]
    assert ids_expr(100, 5, None) == "(pk >= 100 and pk < 105)"
    assert ids_expr(100, 0, None) is None
    assert ids_expr(0, 4, np.array([0, 1, 1, 0, 1], bool)) == "((pk >= 1 and pk < 3))"
    rule = Exclusion(50.0, 10.0, 7, 'r"x', "s")
    assert exclusion_expr(8, 9, rule) == (
        '(pk >= 8 and pk < 17) and (not (robot == "r\\"x" and session == "s") or '
        "(pk < 15 and (stamp <= 40.0 or stamp >= 60.0)))"
    )
    assert "stamp != 50.0" in exclusion_expr(0, 9, Exclusion(50.0, 0.0, 9, "r", "s"))
    assert exclusion_expr(0, 0, rule) is None
    # the robot-session's id runs known: numbers only (Milvus compares strings row by row)
    assert exclusion_expr(8, 9, rule, [(2, 4), (6, 9)]) == (
        "(pk >= 8 and pk < 17) and (not ((pk >= 10 and pk < 12) or (pk >= 14 and pk < 17)) or "
        "(pk < 15 and (stamp <= 40.0 or stamp >= 60.0)))"
    )
    assert exclusion_expr(8, 9, rule, []) == "(pk >= 8 and pk < 17)"  # none of it: all eligible
    many = [(i, i + 1) for i in range(0, 18, 2)]  # 9 runs: the fields again
    assert exclusion_expr(8, 9, rule, many) == exclusion_expr(8, 9, rule)


def test_identity_runs_follow_the_rows_as_they_grow_or_are_replaced():
    runs = IdentityRuns()
    rows = [("a", "s1", 0.0), ("a", "s1", 1.0), ("b", "s1", 2.0)]
    assert runs.of(rows, "a", "s1") == [(0, 2)]
    rows += [("a", "s1", 3.0), ("a", "s1", 4.0)]
    assert runs.of(rows, "a", "s1") == [(0, 2), (3, 5)]
    assert runs.of(rows, "b", "s1") == [(2, 3)]
    assert runs.of(rows, "c", "s1") == []
    assert runs.of([("c", "s1", 0.0)], "c", "s1") == [(0, 1)]  # another list: counted anew
    shorter = rows[:2]
    assert runs.of(shorter, "a", "s1") == [(0, 2)]
    shorter[1] = ("b", "s1", 1.0)  # changed in place below what was counted: counted anew
    assert runs.of(shorter, "a", "s1") == [(0, 1)]


def test_save_and_load_reattach_the_collection(milvus, tmp_path):
    with filled(milvus) as m:
        want = m.search(desc_for(9), 5)
        m.save(tmp_path / "map")
        writer = m._index.writer
    assert sorted(p.name for p in (tmp_path / "map").glob("index-*")) == ["index-1-0.milvus"]
    with PlaceMap.load(tmp_path / "map", "fp") as m:
        assert (len(m), m._index.writer) == (N, writer)
        assert_same_answer(m.search(desc_for(9), 5), want)
        add_range(m, N, N + 3)  # continues under its writer key
        assert m.search(desc_for(N + 1), 1)[0][0] == N + 1
    with PlaceMap.load(tmp_path / "map", "fp", read_only=True) as m:
        assert_same_answer(m.search(desc_for(9), 5), want)


def assert_same_answer(got: list, want: list) -> None:
    """Same ids in the same order; scores to float32 rounding (a server scores a sealed segment
    with other kernels than the growing one it searched before the save: last bits differ)."""
    assert [i for i, _ in got] == [i for i, _ in want]
    np.testing.assert_allclose([s for _, s in got], [s for _, s in want], atol=1e-6)


def test_load_names_and_removes_rows_without_dense_tokens(milvus, tmp_path, caplog):
    """Keyframes added after the last save are in the collection but not in the map folder."""
    m = filled(milvus, 10)
    m.save(tmp_path / "map")
    add_range(m, 10, 13)
    m.close()  # as a crash: never saved again
    with caplog.at_level(logging.WARNING), PlaceMap.load(tmp_path / "map", "fp", read_only=True):
        pass
    assert "3 keyframe(s) ([10, 11, 12]) of this map past its saved 10 keyframes" in caplog.text
    assert "(added after the last save)\n" in caplog.text + "\n"  # read-only: not removed
    caplog.clear()
    with caplog.at_level(logging.WARNING), PlaceMap.load(tmp_path / "map", "fp") as m:
        assert "(added after the last save): removed" in caplog.text
        assert m._index._count(f"pk >= {m._index.base}") == 10


def test_load_inserts_rows_the_collection_lost(milvus, tmp_path, caplog):
    with filled(milvus, 10) as m:
        m.save(tmp_path / "map")
        m._index.client.delete(milvus.milvus_collection, filter=f"pk < {m._index.base + 4}")
    with caplog.at_level(logging.WARNING), PlaceMap.load(tmp_path / "map", "fp") as m:
        assert "held 6 of this map's 10 keyframes; inserting them again" in caplog.text
        assert m.search(desc_for(2), 1)[0][0] == 2


def test_maps_sharing_a_collection_see_only_their_own_rows(milvus):
    """A second run against the same file and collection starts clean: its own writer key."""
    with filled(milvus, 10) as first, PlaceMap(DIM, SHAPE, "fp", index=milvus) as second:
        assert first._index.writer != second._index.writer
        assert second.search(desc_for(3), 5) == []
        for i in range(20, 25):
            second.add(desc_for(i), dense_for(i), meta_for(i))
        assert second.search(desc_for(22), 1)[0][0] == 2
        assert {i for i, _ in second.search(desc_for(22), 10)} == set(range(5))
        assert {i for i, _ in first.search(desc_for(3), 20)} == set(range(10))


def test_clear_forgets_the_rows(milvus):
    with filled(milvus, 6) as m:
        old = m._index.base
        m.clear()
        assert len(m) == 0 and m.search(desc_for(1), 5) == []
        assert m._index._count(f"pk >= {old} and pk < {old + 2**32}") == 0


def test_two_writers_at_once_lose_nothing(milvus):
    """Two maps (robots) of one process writing one collection concurrently."""
    maps = [PlaceMap(DIM, SHAPE, "fp", index=milvus) for _ in range(2)]
    threads = [threading.Thread(target=add_range, args=(m, 0, 25)) for m in maps]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    index = maps[0]._index
    assert index._count("pk >= 0") == 50
    for m in maps:
        assert {i for i, _ in m.search(desc_for(4), 25)} == set(range(25))
        m.close()


def test_a_second_process_cannot_open_a_milvus_lite_file(lite_db, tmp_path):
    """milvus-lite locks its file to one process: a second writer gets a clear error (several
    processes need a Milvus server: test_two_writers.py)."""
    milvus = IndexConfig(kind="milvus", milvus_uri=str(lite_db), milvus_collection="kf_lock")
    with PlaceMap(DIM, SHAPE, "fp", index=milvus):
        code = (
            "from pair_vpr_ros.place_map import PlaceMap, IndexConfig\n"
            f"c = IndexConfig(kind='milvus', milvus_uri={milvus.milvus_uri!r})\n"
            "PlaceMap(8, (4, 8), 'fp', index=c)\n"
        )
        proc = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=120
        )
    assert proc.returncode != 0
    assert (
        f"MapError: cannot connect to milvus-lite file {milvus.milvus_uri} (Open local milvus "
        "failed): milvus-lite lets one process open a file at a time: if another process holds "
        "it, stop that process, use another file, or run a Milvus server for several writers"
    ) in proc.stderr


def test_a_server_that_goes_away_loses_nothing(milvus, caplog):
    with filled(milvus, 5) as m:
        client = make_flaky(m)
        client.down = True
        with caplog.at_level(logging.WARNING):
            for i in range(5, 8):
                assert m.add(desc_for(i), dense_for(i), meta_for(i)) == i  # kept, no error
        assert caplog.text.count("cannot be reached") == 1  # once per outage, not per frame
        assert m.index_diagnostics == {"map_searches_skipped": 0, "map_keyframes_pending": 3}
        with pytest.raises(MapUnavailableError, match="query skipped, 3 keyframe"):
            m.search(desc_for(6), 3)
        assert m.index_diagnostics == {"map_searches_skipped": 1, "map_keyframes_pending": 3}
        client.down = False
        assert m.search(desc_for(6), 1)[0][0] == 6  # the kept keyframes went in first
        assert m.index_diagnostics["map_keyframes_pending"] == 0
        assert m._index._count("pk >= 0") == 8


def test_inserts_whose_reply_was_lost_are_not_duplicated(milvus):
    """milvus-lite hides duplicate keys from count and search; a server keeps both rows, so the
    retry must be an upsert (replaces by key), which is what is checked here."""
    with filled(milvus, 3) as m:
        client = make_flaky(m)
        client.lose_replies = True
        add_range(m, 3, 5)  # stored, but the map cannot know it: kept as pending
        assert client.names == ["insert", "upsert"]
        assert m.index_diagnostics["map_keyframes_pending"] == 2
        client.lose_replies = False
        assert [i for i, _ in m.search(desc_for(4), 5)][0] == 4
        assert client.names[2:] == ["upsert", "search"]
        add_range(m, 5, 6)
        assert client.names[4:] == ["insert"]  # a plain insert again once all are stored
        assert m._index._count("pk >= 0") == 6


def test_the_pipeline_counts_skipped_queries(tiny_model, milvus):
    """Revisits while the server is away: skipped and counted; afterwards the loop is found."""
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(4)]
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT_MATCH), index=milvus)
    frames = [Frame(stamp=float(t), rgb=images[t % 4], frame_id="cam") for t in range(8)]
    list(pipe.process_many(frames[:4]))
    client = make_flaky(pipe.place_map)
    client.down = True
    out = list(pipe.process_many(frames[4:7]))
    assert [o.loop for o in out] == [None] * 3 and [o.keyframe_id for o in out] == [4, 5, 6]
    assert (pipe.counts.map_searches_skipped, pipe.counts.map_keyframes_pending) == (3, 3)
    client.down = False
    (last,) = pipe.process_many(frames[7:])
    assert (last.loop.accepted, last.loop.match_id, last.loop.query_id) == (True, 3, 7)
    assert pipe.counts.map_keyframes_pending == 0 and pipe.counts.loops == 1
    pipe.close()


def test_without_the_extra_the_error_says_what_to_install(monkeypatch, tmp_path):
    milvus = IndexConfig(kind="milvus", milvus_uri=str(tmp_path / "x.db"))  # never connected
    monkeypatch.setitem(sys.modules, "pymilvus", None)
    with pytest.raises(MapError.__mro__[1], match=r"pip install 'pair_vpr_ros\[milvus\]'"):
        PlaceMap(DIM, SHAPE, "fp", index=milvus)


def test_relative_lite_paths_are_made_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = IndexConfig(kind="milvus", milvus_uri="maps/x.db")
    assert config.milvus_uri == str(Path(tmp_path) / "maps" / "x.db")


def test_a_collection_keeps_the_index_type_it_was_made_with(milvus, caplog):
    with filled(milvus, 5):
        pass
    other = replace(milvus, milvus_index="HNSW")
    with caplog.at_level(logging.WARNING), PlaceMap(DIM, SHAPE, "fp", index=other) as m:
        assert m._index.index_type == "FLAT"
        add_range(m, 0, 3)
        assert m.search(desc_for(1), 1)[0][0] == 1
    assert (
        "was made with a FLAT index, milvus_index says HNSW: searching it as FLAT" in caplog.text
    )


def test_map_search_gives_milvus_the_identity_rules(milvus):
    """Issue 22 through the pipeline's MapSearch: the Milvus filter returns what the FAISS
    masks return (own recent keyframes out; another robot or session at once)."""
    from pair_vpr_ros.identity import Identity
    from pair_vpr_ros.loops.map_search import MapSearch

    rows = [("b", "s1", 100.0), ("a", "s1", 101.0), ("a", "s2", 50.0), ("a", "s2", 99.0)]
    with PlaceMap(DIM, SHAPE, "fp", index=milvus) as live, PlaceMap(DIM, SHAPE, "fp") as flat:
        for i, (robot, session, stamp) in enumerate(rows):
            meta = KeyframeMeta(stamp=stamp, robot=robot, session=session)
            for m in (live, flat):
                m.add(desc_for(i), dense_for(i), meta)
        config = DetectorConfig(top_k=10, exclude_recent_s=30.0, exclude_recent_keyframes=1)
        who = Identity("a", "s2")
        got = MapSearch(live).search(desc_for(0), 100.0, who, config)
        want = MapSearch(flat).search(desc_for(0), 100.0, who, config)
        assert sorted(c.id for c in got) == [0, 1, 2]
        assert [(c.id, c.robot, c.session) for c in got] == [
            (c.id, c.robot, c.session) for c in want
        ]


def _rows_in(config: IndexConfig) -> int:
    from pymilvus import MilvusClient

    found = MilvusClient(config.milvus_uri).query(
        config.milvus_collection, filter="pk >= 0", output_fields=["count(*)"]
    )
    return int(found[0]["count(*)"])


def test_closing_a_never_saved_map_deletes_its_rows(milvus, tmp_path, caplog):
    """Rows no saved record names could never be loaded (an interrupted replay): close deletes
    them; rows a saved folder names stay, also through clear()."""
    filled(milvus, 4).close()
    assert _rows_in(milvus) == 0
    with filled(milvus, 3) as m:
        m.save(tmp_path / "map")
        add_range(m, 3, 5)  # past the save: left for the next writable load (or prune-milvus)
    assert _rows_in(milvus) == 5
    with PlaceMap.load(tmp_path / "map", "fp") as m:  # removes the 2 unsaved rows
        m.clear()  # the folder still names its 3 rows: they stay
        add_range(m, 0, 2)
    assert _rows_in(milvus) == 3
    caplog.clear()
    with caplog.at_level(logging.WARNING), PlaceMap.load(tmp_path / "map", "fp") as m:
        assert m.search(desc_for(2), 1)[0][0] == 2 and caplog.text == ""
    m = filled(milvus, 2)
    make_flaky(m).down = True  # Milvus gone at close (or a crash): the rows stay
    with caplog.at_level(logging.WARNING):
        m.close()
    assert (
        f"did not answer (Fail connecting to server on 127.0.0.1:19530): the rows of writer "
        f"{m._index.writer} stay; remove them later with pairvpr-map prune-milvus" in caplog.text
    )
    assert _rows_in(milvus) == 3 + 2
