"""The "ivf" place-map index: exact until trained, ids and exclusion kept through (re)training,
save/load before and after training, the training schedule, an add that fails while training."""

from __future__ import annotations

import logging
from pathlib import Path

import faiss
import numpy as np
import pytest
from test_place_map_persist import SHAPE, dense_for, meta_for

from pair_vpr_ros.place_map import IndexConfig, PlaceMap
from pair_vpr_ros.place_map import ivf as ivf_module
from pair_vpr_ros.place_map.index import DescriptorIndex

DIM = 16
# Trained at 200 and 800 keyframes (growth 4), 4 sqrt(n) lists capped at n/39: 5, then 20.
SMALL = IndexConfig(kind="ivf", train_at=200, exact_below=0)


def clustered(n: int, seed: int = 0, centres: int = 12) -> np.ndarray:
    """[n, DIM] unit vectors around `centres` random directions (places revisited)."""
    rng = np.random.default_rng(seed)
    c = rng.normal(size=(centres, DIM))
    x = c[rng.integers(0, centres, n)] + 0.3 * rng.normal(size=(n, DIM))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def near(descs: np.ndarray, every: int = 30) -> np.ndarray:
    """Queries: every `every`-th descriptor moved a little (revisits)."""
    x = descs[::every] + 0.1 * np.random.default_rng(9).normal(size=descs[::every].shape)
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def fill(m: PlaceMap, descs: np.ndarray, start: int = 0) -> None:
    for i, d in enumerate(descs, start):
        assert m.add(d, dense_for(i), meta_for(i)) == i


def exact(descs: np.ndarray, q: np.ndarray, k: int, eligible: np.ndarray) -> list[int]:
    sims = descs[eligible] @ q
    return eligible[np.argsort(-sims, kind="stable")[:k]].tolist()


def test_trains_on_schedule_and_keeps_ids() -> None:
    descs = clustered(1000)
    with PlaceMap(DIM, SHAPE, "fp", index=SMALL) as m:
        fill(m, descs[:199])
        assert isinstance(m._index._index, faiss.IndexFlatIP) and m._index.last_training is None
        fill(m, descs[199:200], 199)
        first = m._index.last_training
        assert (first.keyframes, first.nlist, first.sample) == (200, 5, 200)
        fill(m, descs[200:799], 200)
        assert m._index.last_training is first  # not again before 4 x 200
        fill(m, descs[799:], 799)
        again = m._index.last_training
        assert (again.keyframes, again.nlist, again.sample) == (800, 20, 800)
        index = m._index._index
        assert isinstance(index, faiss.IndexIVFFlat) and index.ntotal == 1000
        # ids are insertion positions: every stored vector is the one added as that id
        np.testing.assert_allclose(m.get_desc(range(1000)), descs, atol=1e-6)
        lists = [faiss.rev_swig_ptr(index.invlists.get_ids(i), index.invlists.list_size(i))
                 for i in range(index.nlist)]  # fmt: skip
        assert all(np.all(np.diff(ids) > 0) for ids in lists)  # sorted: range bisection is valid
        assert np.array_equal(np.sort(np.concatenate(lists)), np.arange(1000))


def test_all_lists_probed_equals_flat_search() -> None:
    descs = clustered(900)
    queries = near(descs)
    config = IndexConfig(kind="ivf", train_at=200, nprobe=1000, exact_below=0)
    with PlaceMap(DIM, SHAPE, "fp", index=config) as m, PlaceMap(DIM, SHAPE, "fp") as flat:
        fill(m, descs)
        fill(flat, descs)
        assert isinstance(m._index._index, faiss.IndexIVFFlat)
        for q in queries:
            assert [i for i, _ in m.search(q, 10)] == [i for i, _ in flat.search(q, 10)]


def test_few_probes_find_clustered_neighbours() -> None:
    """One list of 20 probed: the query's own cluster holds most of its neighbours."""
    descs = clustered(900)
    queries = near(descs)
    config = IndexConfig(kind="ivf", train_at=200, nprobe=1, exact_below=0)
    with PlaceMap(DIM, SHAPE, "fp", index=config) as m:
        fill(m, descs)
        every = np.arange(900)
        hits = [len({i for i, _ in m.search(q, 10)} & set(exact(descs, q, 10, every)))
                for q in queries]  # fmt: skip
        assert 0.7 <= np.mean(hits) / 10 < 1.0  # approximate (0.82 here), and not by much


def test_exclusion_after_training(monkeypatch) -> None:
    descs = clustered(900)
    with PlaceMap(DIM, SHAPE, "fp", index=replace_nprobe(4)) as m:
        fill(m, descs)
        calls = []
        probe = ivf_module.IvfIndex._probe
        monkeypatch.setattr(
            ivf_module.IvfIndex, "_probe", lambda s, *a: calls.append(a[2]) or probe(s, *a)
        )
        q = descs[850]
        hits = m.search(q, 5, max_id=400)
        assert all(i <= 400 for i, _ in hits) and len(hits) == 5
        assert hits[0][0] == exact(descs, q, 1, np.arange(401))[0]
        allowed = np.zeros(900, bool)
        allowed[::7] = True
        hits = m.search(q, 5, allowed=allowed)
        assert all(i % 7 == 0 for i, _ in hits) and len(hits) == 5
        # Three eligible ids, most likely outside the probed lists: the exact fallback finds all
        allowed[:] = False
        allowed[[3, 500, 899]] = True
        calls.clear()
        assert sorted(i for i, _ in m.search(q, 10, allowed=allowed)) == [3, 500, 899]
        assert calls[-1] == 20  # the last pass scanned every list
        # exact_below: few eligible ids are scanned exactly at once
        m._index.config = replace_nprobe(4, exact_below=100)
        calls.clear()
        assert [i for i, _ in m.search(q, 3, max_id=50)] == exact(descs, q, 3, np.arange(51))
        assert calls == [20]


def replace_nprobe(nprobe: int, exact_below: int = 0) -> IndexConfig:
    return IndexConfig(kind="ivf", train_at=200, nprobe=nprobe, exact_below=exact_below)


@pytest.mark.parametrize("count", [150, 900])  # saved before / after training
def test_save_load_keeps_kind_and_results(tmp_path: Path, count: int) -> None:
    descs = clustered(1000)
    queries = near(descs, 100)
    with PlaceMap(DIM, SHAPE, "fp", index=replace_nprobe(3)) as m:
        fill(m, descs[:count])
        before = [m.search(q, 5, max_id=count - 20) for q in queries]
        m.save(tmp_path / "map")
    with PlaceMap.load(tmp_path / "map") as m:
        assert m.index_config == replace_nprobe(3)
        want = faiss.IndexIVFFlat if count > 200 else faiss.IndexFlatIP
        assert type(m._index._index) is want
        assert [m.search(q, 5, max_id=count - 20) for q in queries] == before
        fill(m, descs[count:], count)  # goes on training on schedule after the load
        assert m._index._index.nlist == 20  # trained at 800: after the load, or before the save
        assert (m._index.last_training is None) == (count > 800)
        np.testing.assert_allclose(m.get_desc(range(1000)), descs, atol=1e-6)


def test_bulk_add_trains_once_and_failed_training_changes_nothing(monkeypatch) -> None:
    descs = clustered(1000)
    index = DescriptorIndex(DIM, SMALL)
    index.add(descs[:900])  # crosses 200 and 800 at once: one training, at 900
    assert index.last_training.keyframes == 900 and len(index) == 900
    monkeypatch.setattr(faiss.IndexIVFFlat, "train", lambda *a: (_ for _ in ()).throw(MemoryError))
    with PlaceMap(DIM, SHAPE, "fp", index=SMALL) as m:
        fill(m, descs[:199])
        with pytest.raises(MemoryError):
            fill(m, descs[199:200], 199)
        assert len(m) == 199 and isinstance(m._index._index, faiss.IndexFlatIP)
        assert len(m.all_meta()) == 199
        monkeypatch.undo()
        fill(m, descs[199:300], 199)  # the next add trains
        assert m._index.last_training.keyframes == 200
        np.testing.assert_allclose(m.get_desc(range(300)), descs[:300], atol=1e-6)


def test_schedule_and_list_count() -> None:
    never = DescriptorIndex(DIM, IndexConfig(kind="ivf", train_at=100, retrain_growth=0))
    stages = [never._ivf.stage(n) for n in (99, 100, 10**6)]
    assert stages == [-1, 0, 0]
    ivf = DescriptorIndex(DIM, IndexConfig(kind="ivf", nlist=1000))._ivf
    assert ivf.first_training_size() == 39_000  # 39 per list beats train_at 25,000
    assert [ivf.stage(n) for n in (38_999, 39_000, 155_999, 156_000, 624_000)] == [-1, 0, 0, 1, 2]
    auto = DescriptorIndex(DIM, IndexConfig(kind="ivf"))._ivf
    assert [auto.nlist_for(n) for n in (25_000, 100_000, 400_000)] == [632, 1265, 2530]
    assert auto.nlist_for(1000) == 25  # at most n / 39 points per list


def test_single_adds_run_on_search_threads(monkeypatch) -> None:
    """A one-keyframe add to a trained index runs on `search_threads` OpenMP threads (the
    fan-out only waits on a busy machine); the caller's setting is restored."""
    seen = []
    index = DescriptorIndex(DIM, IndexConfig(kind="ivf", train_at=200, search_threads=1))
    index.add(clustered(300))
    add = faiss.IndexIVFFlat.add
    monkeypatch.setattr(
        faiss.IndexIVFFlat,
        "add",
        lambda s, x: seen.append(faiss.omp_get_max_threads()) or add(s, x),
    )
    before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(3)
    try:
        index.add(clustered(1, seed=1))
        assert seen == [1] and faiss.omp_get_max_threads() == 3 and len(index) == 301
    finally:
        faiss.omp_set_num_threads(before)


def test_training_is_logged_as_a_warning(caplog) -> None:
    """The add that trains pauses its caller: a warning says how long (the node shows it)."""
    index = DescriptorIndex(DIM, SMALL)
    with caplog.at_level(logging.WARNING, logger="pair_vpr_ros.place_map.ivf"):
        index.add(clustered(250))
    assert "ivf index trained at 250 keyframes: 6 lists, k-means on 250; this add paused" in (
        caplog.text
    )
