"""`pairvpr-map` on maps whose index is Milvus (milvus-lite in tmp_path, and a server): merge
(milvus with milvus, milvus with flat; the merged map answers as its inputs did; a failed merge
leaves no rows) and prune-milvus (stale rows removed, every row a saved map refers to kept)."""

from __future__ import annotations

import logging
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from bad_input import make_flaky, saved_map_digest, store_text
from map_fixtures import DENSE, DIM, make_map

from pair_vpr_ros.offline.map_cli import main
from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap, persist


def _rows(config: IndexConfig) -> int:
    """Rows in the collection of `config` (a client of this process; the file is shared)."""
    from pymilvus import MilvusClient

    client = MilvusClient(config.milvus_uri)
    found = client.query(config.milvus_collection, filter="pk >= 0", output_fields=["count(*)"])
    return int(found[0]["count(*)"])


def _results(m: PlaceMap, queries: np.ndarray) -> list[list[tuple[int, float]]]:
    return [m.search(q, 10) for q in queries]


def _inputs_answer(inputs: list[Path], queries: np.ndarray) -> list[list[tuple[int, float]]]:
    """What the inputs answer, their ids shifted as the merge numbers them, best first."""
    answers = [[] for _ in queries]
    offset = 0
    for d in inputs:
        with PlaceMap.load(d, read_only=True) as m:
            for row, q in enumerate(queries):
                answers[row] += [(i + offset, s) for i, s in m.search(q, 10)]
            offset += len(m)
    return [sorted(a, key=lambda hit: -hit[1])[:10] for a in answers]


def _assert_same(got, want) -> None:
    assert [[i for i, _ in hits] for hits in got] == [[i for i, _ in hits] for hits in want]
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose([s for _, s in g], [s for _, s in w], atol=1e-5)


QUERIES = np.random.default_rng(9).normal(size=(6, DIM)).astype(np.float32)


def test_merge_two_milvus_maps(milvus, tmp_path, capsys):
    a = make_map(tmp_path / "a", "r1", "mon", 3, seed=1, index=milvus)
    b = make_map(tmp_path / "b", "r2", "mon", 4, seed=2, index=milvus)
    before = {d: saved_map_digest(d) for d in (a, b)}
    assert main(["merge", str(a), str(b), "--out", str(tmp_path / "c"), "--quiet"]) == 0
    assert (
        capsys.readouterr().out
        == f"merged 7 keyframes of {a} (3), {b} (4) into {tmp_path / 'c'}\n"
    )
    want = _inputs_answer([a, b], QUERIES)
    with (
        PlaceMap.load(tmp_path / "c", read_only=True) as c,
        PlaceMap.load(a, read_only=True) as ma,
        PlaceMap.load(b, read_only=True) as mb,
    ):
        assert c.index_config == milvus and len(c) == 7
        assert len({c._index.writer, ma._index.writer, mb._index.writer}) == 3  # own rows
        _assert_same(_results(c, QUERIES), want)
        for source, offset in ((ma, 0), (mb, 3)):
            for old in source.all_meta():
                assert c.meta(old.id + offset) == replace(old, id=old.id + offset)
                assert c.search(source.get_desc([old.id])[0], 1)[0][0] == old.id + offset
    assert {d: saved_map_digest(d) for d in (a, b)} == before
    assert _rows(milvus) == 3 + 4 + 7  # the inputs' rows untouched, the merged map's added


def test_merge_a_milvus_map_with_a_flat_one(milvus, tmp_path, capsys):
    """Inputs of any kinds mix; the merged map takes the first input's index (or --index)."""
    m = make_map(tmp_path / "m", "r1", "mon", 3, seed=1, index=milvus)
    f = make_map(tmp_path / "f", "r2", "mon", 2, seed=2)
    want_mf, want_fm = _inputs_answer([m, f], QUERIES), _inputs_answer([f, m], QUERIES)
    assert main(["merge", str(m), str(f), "--out", str(tmp_path / "mf"), "--quiet"]) == 0
    assert main(["merge", str(f), str(m), "--out", str(tmp_path / "fm"), "--quiet"]) == 0
    other = replace(milvus, milvus_collection=milvus.milvus_collection + "_x")
    flags = ["--index", "milvus", "--milvus-uri", other.milvus_uri]
    flags += ["--milvus-collection", other.milvus_collection, "--quiet"]
    assert main(["merge", str(f), str(m), "--out", str(tmp_path / "fm2"), *flags]) == 0
    mf3 = ["merge", str(m), str(f), "--out", str(tmp_path / "mf3"), "--index", "flat"]
    assert main([*mf3, "--quiet"]) == 0
    capsys.readouterr()
    for out, config, want in (("mf", milvus, want_mf), ("fm", IndexConfig(), want_fm),
                              ("mf3", IndexConfig(), want_mf)):  # fmt: skip
        with PlaceMap.load(tmp_path / out, read_only=True) as merged:
            assert (merged.index_config, len(merged)) == (config, 5)
            _assert_same(_results(merged, QUERIES), want)
    with PlaceMap.load(tmp_path / "fm2", read_only=True) as merged:
        assert merged.index_config == IndexConfig(
            kind="milvus", milvus_uri=other.milvus_uri, milvus_collection=other.milvus_collection
        )  # the first map's settings (defaults) and the flags
        _assert_same(_results(merged, QUERIES), want_fm)
    assert _rows(milvus) == 3 + 5 and _rows(other) == 5

    # --index milvus needs a URI when the first map has none; milvus flags need --index milvus
    assert main(["merge", str(f), str(m), "--out", str(tmp_path / "x"), "--index", "milvus"]) == 1
    assert capsys.readouterr().err == (
        "error: --index milvus needs --milvus-uri (a milvus-lite .db file or http://host:19530): "
        f"the first map, {f}, has a 'flat' index and no Milvus settings\n"
    )
    args = ["merge", str(m), str(f), "--out", str(tmp_path / "x"), "--index", "flat"]
    assert main([*args, "--milvus-collection", "kf"]) == 1
    assert capsys.readouterr().err == (
        "error: --milvus-uri and --milvus-collection apply to a milvus index only, the merged "
        "map's index is 'flat': add --index milvus or leave them out\n"
    )
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("step", ["dense", "index", "manifest"])
def test_a_merge_that_dies_removes_the_rows_it_wrote(milvus, tmp_path, capsys, monkeypatch, step):
    a = make_map(tmp_path / "a", "r1", "mon", 3, seed=1, index=milvus)
    b = make_map(tmp_path / "b", "r2", "mon", 2, seed=2, index=milvus)

    def die(reached: str) -> None:
        if reached == step:
            raise KeyboardInterrupt

    monkeypatch.setattr(persist, "_SAVE_HOOK", die)
    assert main(["merge", str(a), str(b), "--out", str(tmp_path / "c"), "--quiet"]) == 130
    assert capsys.readouterr().err == "error: interrupted\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]
    assert _rows(milvus) == 5  # only the inputs' rows


# ----------------------------------------------------------------------------- prune-milvus


def _unsaved_run(config: IndexConfig, n: int) -> None:
    """A map that writes `n` rows and is never saved, and cannot delete them when it closes
    (Milvus gone then, or a crash)."""
    m = PlaceMap(DIM, DENSE, "model-a", index=config)
    for i in range(n):
        m.add(
            QUERIES[i % len(QUERIES)],
            np.zeros(DENSE),
            KeyframeMeta(stamp=i, robot="r9", session="crash"),
        )
    make_flaky(m).down = True
    m.close()


@pytest.fixture
def site(tmp_path, store):
    """A milvus-lite file inside the maps folder (prune must not take it for a map), or a
    collection of its own on the test server."""
    from milvus_fixtures import drop, new_name

    (tmp_path / "maps").mkdir()
    lite = store.endswith(".db")
    uri = str(tmp_path / "maps" / "site.db") if lite else store
    name = "kf" if lite else new_name("site")
    yield IndexConfig(kind="milvus", milvus_uri=uri, milvus_collection=name, milvus_index="FLAT")
    if not lite:
        drop(uri, name)


def test_prune_removes_stale_rows_and_keeps_every_saved_one(site, tmp_path, capsys, caplog):
    maps = tmp_path / "maps"
    a = make_map(maps / "a", "r1", "mon", 3, seed=1, index=site)
    shutil.copytree(a, maps / "backup" / "a")  # a copy: the same writer key
    make_map(maps / "old" / "f", "r1", "tue", 2, seed=3)  # a flat map: nothing to do with it
    with PlaceMap.load(a) as m:  # saved into b, again, then 1 keyframe more never saved
        writer_a = m._index.writer
        b = m.save(maps / "deep" / "b")
        m.add(QUERIES[0], np.zeros(DENSE), KeyframeMeta(stamp=50.0, robot="r1", session="mon"))
        m.save(b)
        m.add(QUERIES[1], np.zeros(DENSE), KeyframeMeta(stamp=51.0, robot="r1", session="mon"))
        writer_b = m._index.writer
        make_flaky(m).down = True  # a crash: the 5th row stays
    assert writer_b != writer_a  # a save into a new folder writes its rows under its own key
    _unsaved_run(site, 4)
    writer_u = _stale_writer(site, {writer_a, writer_b})
    before = _inputs_answer([a], QUERIES), _inputs_answer([b], QUERIES)
    args = ["prune-milvus", site.milvus_uri, "--maps", str(maps)]
    args += ["--collection", site.milvus_collection]
    head = f"collection {site.milvus_collection!r} in {store_text(site)}: {{}} rows, 7 kept for "
    head += "3 saved "
    stale = [
        f"stale: writer {writer_b}: 1 rows, ids 4..4 (past its saved 4), r1/mon",
        f"stale: writer {writer_u}: 4 rows, ids 0..3 (no saved map), r9/crash",
    ]
    stale.sort(key=lambda line: int(line.split()[2].rstrip(":")))
    assert main(args) == 0  # a dry run
    assert capsys.readouterr().out.splitlines() == [
        head.format(12) + "map(s), 5 stale", *stale,
        "dry run: 5 stale rows not removed; pass --yes to remove",
    ]  # fmt: skip
    assert _rows(site) == 12
    assert main([*args, "--yes"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "removed 5 stale rows; 7 remain"
    assert _rows(site) == 7
    assert main([*args, "--yes"]) == 0
    assert capsys.readouterr().out == head.format(7) + "map(s), 0 stale\n"
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # no saved map lost a row or holds a stale one
        assert (_inputs_answer([a], QUERIES), _inputs_answer([b], QUERIES)) == before
        for d in (a, maps / "backup" / "a", b):
            with PlaceMap.load(d) as m:
                assert len(m) == {b: 4}.get(d, 3)
    assert caplog.text == ""
    assert _rows(site) == 7


def _stale_writer(config: IndexConfig, known: set[int]) -> int:
    from pymilvus import MilvusClient

    client = MilvusClient(config.milvus_uri)
    rows = client.query(config.milvus_collection, filter="pk >= 0", output_fields=["pk"])
    return ({int(r["pk"]) >> 32 for r in rows} - known).pop()


def test_a_saved_map_not_given_gets_its_rows_back_at_load(site, tmp_path, capsys, caplog):
    """Prune trusts --maps; a map left out loses its rows, and its next load inserts them
    again from its own copy (docs/milvus.md)."""
    a = make_map(tmp_path / "a", "r1", "mon", 3, seed=1, index=site)
    want = _inputs_answer([a], QUERIES)
    args = ["prune-milvus", site.milvus_uri, "--maps", str(tmp_path / "maps"), "--collection"]
    assert main([*args, site.milvus_collection, "--yes"]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "removed 3 stale rows; 0 remain"
    with caplog.at_level(logging.WARNING), PlaceMap.load(a) as m:
        assert "held 0 of this map's 3 keyframes; inserting them again" in caplog.text
        _assert_same(_results(m, QUERIES), want)
    _assert_same(_inputs_answer([a], QUERIES), want)
