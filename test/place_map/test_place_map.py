"""PlaceMap in memory: add/search (flat, HNSW), recent-frame exclusion, dense tokens, metadata."""

from __future__ import annotations

import faiss
import numpy as np
import pytest
from test_place_map_persist import stored

from pair_vpr_ros.errors import ConfigError, MapError
from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.dense_codec import decode, encode, entry_bytes, head_bytes
from pair_vpr_ros.place_map.index import DescriptorIndex

DIM, SHAPE = 8, (4, 8)
HNSW_NO_SHORTCUT = IndexConfig(kind="hnsw", exact_below=0)  # always walk the HNSW graph
IVF_EARLY = IndexConfig(kind="ivf", train_at=39, exact_below=0)  # lists from 39 keyframes on


def unit(i: int) -> np.ndarray:
    v = np.zeros(DIM, np.float32)
    v[i] = 1.0
    return v


def dense_for(i: int) -> np.ndarray:
    return (np.arange(32, dtype=np.float32).reshape(SHAPE) * 0.25 + i).astype(np.float32)


def random_descs(n: int, seed: int = 0) -> np.ndarray:
    x = np.random.default_rng(seed).normal(size=(n, DIM)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def fill(m: PlaceMap, descs: np.ndarray) -> None:
    for i, d in enumerate(descs):
        assert m.add(d, dense_for(i), KeyframeMeta(stamp=float(i), frame_id="cam")) == i


@pytest.fixture(params=["flat", "hnsw", "ivf"])
def kind(request) -> str | IndexConfig:
    return {"flat": "flat", "hnsw": HNSW_NO_SHORTCUT, "ivf": IVF_EARLY}[request.param]


def test_search_exact_ids_and_similarities(kind) -> None:
    with PlaceMap(DIM, SHAPE, "fp", index=kind) as m:
        fill(m, np.stack([unit(i) for i in range(5)]))
        q = 0.8 * unit(1) + 0.6 * unit(3)
        hits = m.search(q, 2)
        assert [h[0] for h in hits] == [1, 3]
        assert [h[1] for h in hits] == pytest.approx([0.8, 0.6], abs=1e-6)
        # The query is normalised before searching: scale does not change similarities.
        assert m.search(10 * q, 1)[0][1] == pytest.approx(0.8, abs=1e-6)


def test_max_id_excludes_recent_frames(kind, monkeypatch) -> None:
    if kind == HNSW_NO_SHORTCUT:  # the HNSW graph walk itself honours the selector (no exact scan)
        monkeypatch.setattr(DescriptorIndex, "_storage", lambda self: pytest.fail("exact scan"))
    descs = random_descs(60)
    with PlaceMap(DIM, SHAPE, "fp", index=kind) as m:
        fill(m, descs)
        q = descs[50]  # its nearest neighbours are mostly recent; only ids <= 20 may come back
        hits = m.search(q, 5, max_id=20)
        expect = np.argsort(-(descs[:21] @ q))[:5]
        assert [h[0] for h in hits] == expect.tolist()
        assert [h[1] for h in hits] == pytest.approx((descs[expect] @ q).tolist(), abs=1e-5)
        assert m.search(q, 3, max_id=0) == [(0, pytest.approx(float(descs[0] @ q), abs=1e-5))]
        assert m.search(q, 3, max_id=-1) == []


def test_k_larger_than_eligible_returns_fewer_and_no_padding(kind) -> None:
    with PlaceMap(DIM, SHAPE, "fp", index=kind) as m:
        assert m.search(unit(0), 5) == []
        fill(m, np.stack([unit(i) for i in range(4)]))
        assert sorted(i for i, _ in m.search(unit(0), 10)) == [0, 1, 2, 3]
        assert [i for i, _ in m.search(unit(2), 10, max_id=2)][0] == 2
        assert len(m.search(unit(2), 10, max_id=2)) == 3
        assert m.search(unit(2), 0) == []


def test_search_threads_are_restored() -> None:
    before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(3)  # searches run on 1 thread, then give back the caller's 3
    try:
        with PlaceMap(DIM, SHAPE, "fp", index=IndexConfig(search_threads=1)) as m:
            fill(m, random_descs(3))
            assert len(m.search(unit(0), 2)) == 2
        assert faiss.omp_get_max_threads() == 3
    finally:
        faiss.omp_set_num_threads(before)


def test_hnsw_shortcut_and_config_validation() -> None:
    descs = random_descs(40, seed=3)
    with PlaceMap(DIM, SHAPE, "fp", index="hnsw") as m:  # 40 eligible <= exact_below: exact scan
        fill(m, descs)
        expect = np.argsort(-(descs[:31] @ descs[35]))[:4].tolist()
        assert [i for i, _ in m.search(descs[35], 4, max_id=30)] == expect
        assert m.index_config.hnsw_m == 32
    with pytest.raises(ConfigError, match="must be one of"):
        PlaceMap(DIM, SHAPE, "fp", index="pq")
    with pytest.raises(ConfigError, match="ef_search must be an integer >= 1"):
        IndexConfig(kind="hnsw", ef_search=0)


@pytest.mark.parametrize("codec", ["p4", "q4", "q4a", "f16"])
def test_dense_round_trip(codec: str) -> None:
    index = IndexConfig(dense_codec=codec)
    with PlaceMap(DIM, SHAPE, "fp", index, dense_cache_size=2) as m:
        fill(m, random_descs(5))
        out = m.get_dense([3, 0, 3, 4])
        assert out.dtype == np.float16 and out.shape == (4, *SHAPE)
        for row, i in zip(out, [3, 0, 3, 4], strict=True):
            want = dense_for(i).astype(np.float16)
            if codec == "f16":
                np.testing.assert_array_equal(row, want)
            else:  # 4 bits: within half a step of each value (q4, and p4 before its basis: max
                # |x| of the channel / 7; q4a: (max - min) / 15, up to 2.2 % more as a code of
                # 32 steps an octave)
                step = np.abs(want).max(axis=0).astype(np.float32) / 7
                if codec == "q4a":
                    step = np.ptp(want, axis=0).astype(np.float32) / 15 * 1.03
                assert (np.abs(row - want) <= 0.5 * step + 1e-2).all()
                assert not np.array_equal(row, want)
        assert m.get_dense([]).shape == (0, *SHAPE)
        np.testing.assert_allclose(m.get_desc([1, 2]), random_descs(5)[1:3], atol=1e-6)


def test_q4a_keeps_constant_channels_and_zeros() -> None:
    tokens = np.zeros((4, 8), np.float16)
    tokens[:, 1], tokens[:, 2], tokens[:, 3] = 0.808, -1234.0, np.arange(4)
    back = decode(encode(tokens, "q4a"), (4, 8), "q4a").astype(np.float32)
    # half a step: a channel's step reaches its centre from an int8 zero point (|c| / 120) and
    # spans its range in 15, and is at least 1/251 of the largest step (8 octaves of codes)
    floor = 1234 / 120 / 251
    bound = 0.5 * 1.03 * np.array([floor, max(0.808 / 120, floor), 1234 / 120, max(3 / 15, floor)])
    assert (np.abs(back - tokens).max(axis=0)[:4] <= bound).all()
    assert (back[:, 4:] == 0).all() and entry_bytes((529, 768), "q4a") == 204_676


def test_bytes_per_keyframe(tmp_path) -> None:
    with PlaceMap(512, (529, 768), index=IndexConfig(dense_codec="f16")) as m:
        assert m.bytes_per_keyframe == 529 * 768 * 2 + 512 * 4  # ViT-B/322: float16 + float32
    for codec in ("p4", "q4"):  # the default p4: q4's bytes (4 bits + a float16 scale a channel)
        with PlaceMap(512, (529, 768), index=IndexConfig(dense_codec=codec)) as m:
            assert m.bytes_per_keyframe == 529 * 768 // 2 + 768 * 2 + 512 * 4 <= 202 * 1024
    with PlaceMap(DIM, SHAPE, "fp") as m:
        assert m.index_config.dense_codec == "p4"
        fill(m, random_descs(3))
        m.save(tmp_path / "map")
        (dense,) = (tmp_path / "map").glob("dense-*.p4")  # p4's head holds its basis
        size = head_bytes(SHAPE, "p4") + 3 * (m.bytes_per_keyframe - 4 * DIM)
        assert dense.stat().st_size == size


def test_metadata_round_trip_with_and_without_pose() -> None:
    pose = (1.0, -2.5, 3.0, 0.0, 0.0, 0.70710678, 0.70710678)
    with PlaceMap(DIM, SHAPE, "fp") as m:
        first = KeyframeMeta(id=99, stamp=12.5, frame_id="cam", pose=pose)
        a = m.add(unit(0), dense_for(0), first)
        b = m.add(unit(1), dense_for(1), KeyframeMeta(stamp=13.0, frame_id="cam2", source="bagB"))
        assert (a, b) == (0, 1)  # ids come from the map, never from the caller
        assert m.meta(0) == KeyframeMeta(0, 12.5, "cam", pose, "")
        assert m.meta(1) == KeyframeMeta(1, 13.0, "cam2", None, "bagB")
        assert m.all_meta() == [m.meta(0), m.meta(1)]
        with pytest.raises(MapError, match=r"keyframe 2 is not in the map \(ids 0\.\.1\)"):
            m.meta(2)


def test_clear_restarts_ids() -> None:
    with PlaceMap(DIM, SHAPE, "fp") as m:
        fill(m, random_descs(3))
        m.clear()
        assert len(m) == 0 and m.search(unit(0), 3) == [] and m.all_meta() == []
        assert m.add(unit(5), dense_for(7), KeyframeMeta(stamp=1.0)) == 0
        np.testing.assert_array_equal(m.get_dense([0])[0], stored(dense_for(7)))


@pytest.mark.parametrize(
    ("desc", "dense", "meta", "message"),
    [
        (np.ones(7), dense_for(0), KeyframeMeta(), r"descriptor must have shape \[8\], got \[7\]"),
        (np.zeros(8), dense_for(0), KeyframeMeta(), "descriptor must be finite and non-zero"),
        (np.full(8, np.nan), dense_for(0), KeyframeMeta(), "finite and non-zero"),
        (np.ones(8), np.ones((4, 7)), KeyframeMeta(), r"must have shape \[4, 8\], got \[4, 7\]"),
        (np.ones(8), np.full(SHAPE, 1e6), KeyframeMeta(), "beyond the float16 range"),
        (np.ones(8), dense_for(0), KeyframeMeta(pose=(1, 2, 3)), "pose must be 7 finite numbers"),
        (np.ones(8), dense_for(0), KeyframeMeta(stamp=float("inf")), "stamp must be a finite"),
        (np.ones(8), dense_for(0), {"stamp": 1.0}, "must be a KeyframeMeta, got dict"),
    ],
)
def test_bad_input_is_refused_and_leaves_map_unchanged(desc, dense, meta, message) -> None:
    with PlaceMap(DIM, SHAPE, "fp") as m:
        fill(m, random_descs(2))
        with pytest.raises(MapError, match=message):
            m.add(desc, dense, meta)
        assert len(m) == 2 and len(m.all_meta()) == 2
        assert m.add(unit(0), dense_for(9), KeyframeMeta()) == 2


def test_bad_ids_and_closed_map() -> None:
    m = PlaceMap(DIM, SHAPE, "fp")
    fill(m, random_descs(2))
    with pytest.raises(MapError, match=r"keyframe ids \[2, -1\] are not in the map"):
        m.get_dense([0, 2, -1])
    with pytest.raises(MapError, match="1-D sequence of ints"):
        m.get_desc([0.5])
    with pytest.raises(MapError, match="search k must be >= 0"):
        m.search(unit(0), -1)
    work = m._tmp
    assert work.is_dir()
    m.close()
    assert not work.exists()  # the working folder is removed
    with pytest.raises(MapError, match="this PlaceMap is closed"):
        m.search(unit(0), 1)
    m.close()  # idempotent


def test_hnsw_walk_missing_eligible_ids_falls_back_to_exact(monkeypatch) -> None:
    descs = random_descs(500, seed=5)
    calls = []
    storage = DescriptorIndex._storage
    monkeypatch.setattr(DescriptorIndex, "_storage", lambda self: calls.append(1) or storage(self))
    config = IndexConfig(kind="hnsw", exact_below=0, ef_search=5)
    with PlaceMap(DIM, SHAPE, "fp", index=config) as m:
        for d in descs:
            m.add(d, dense_for(0), KeyframeMeta())
        hits = m.search(descs[400], 5, max_id=5)  # 6 eligible ids among 500
        assert [i for i, _ in hits] == np.argsort(-(descs[:6] @ descs[400]))[:5].tolist()
        assert calls  # the exact scan answered


@pytest.mark.parametrize(
    "config", ["flat", HNSW_NO_SHORTCUT, IndexConfig(kind="hnsw"), IVF_EARLY, "ivf"]
)
def test_search_only_among_allowed_ids(config) -> None:
    descs = random_descs(60, seed=7)
    allowed = np.zeros(50, bool)
    allowed[[3, 10, 11, 40, 49]] = True  # gaps: a bitmap selector; ids >= 50 never
    with PlaceMap(DIM, SHAPE, "fp", index=config) as m:
        fill(m, descs)
        expect = [
            int(i) for i in np.flatnonzero(allowed)[np.argsort(-(descs[:50][allowed] @ descs[55]))]
        ]
        assert [i for i, _ in m.search(descs[55], 10, allowed=allowed)] == expect
        assert [i for i, _ in m.search(descs[55], 2, allowed=allowed)] == expect[:2]
        prefix = np.ones(20, bool)  # a prefix: the range selector, as max_id=19
        assert m.search(descs[55], 4, allowed=prefix) == m.search(descs[55], 4, max_id=19)
        assert m.search(descs[55], 4, allowed=np.zeros(60, bool)) == []
        assert [i for i, _ in m.search(descs[55], 9, max_id=10, allowed=allowed)] == sorted(
            [3, 10], key=lambda i: -float(descs[i] @ descs[55])
        )
