"""Dense codec p4 (dense_codec.py, dense_store.py): q4 entries before the basis, one basis per
map fitted on them (for the decoder's W), fixed-size entries after it; reload, merge, compact."""

from __future__ import annotations

from array import array
from pathlib import Path

import numpy as np
import pytest

from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.dense_codec import (
    BASIS_FROM,
    _grid,
    _toward,
    decode,
    encode,
    entry_bytes,
    head_bytes,
)
from pair_vpr_ros.place_map.dense_store import DenseStore
from pair_vpr_ros.place_map.growth.compact import compact_map
from pair_vpr_ros.place_map.merge import merge_maps

SHAPE, DIM = (64, 32), 8
P4 = IndexConfig(dense_codec="p4")


def tokens(seed: int, count: int, rank: int = 6) -> np.ndarray:
    """count keyframes [count, N, D] float16 of correlated channels off zero (as ViT tokens: a
    few directions carry most of the variance, each channel has its own offset)."""
    rng = np.random.default_rng(seed)
    mix = np.random.default_rng(7).normal(size=(rank, SHAPE[1])) * 2.0
    offset = np.random.default_rng(8).normal(size=SHAPE[1])
    x = rng.normal(size=(count, SHAPE[0], rank)) @ mix + offset
    return (x + 0.05 * rng.normal(size=x.shape)).astype(np.float16)


def weight() -> np.ndarray:
    """A decoder's first layer W [D, D] (square, well conditioned)."""
    return np.eye(SHAPE[1]) + 0.3 * np.random.default_rng(9).normal(size=(SHAPE[1],) * 2)


def store(path: Path, data: np.ndarray, w: np.ndarray | None = None) -> DenseStore:
    s = DenseStore(path, SHAPE, codec="p4", weight=w, owned=True)  # as a new map's
    for t in data:
        s.append(np.ascontiguousarray(t))
    return s


def q4(t: np.ndarray) -> np.ndarray:
    return decode(encode(t, "q4"), SHAPE, "q4")


def test_a_store_reopened_before_the_fit_keeps_its_first_entries_as_q4(tmp_path: Path) -> None:
    """Reopened (a loaded map) before the fit, the float16 tokens of its first entries are
    gone: the basis is fitted on their q4 form and they stay q4; later entries use the basis."""
    data = tokens(1, BASIS_FROM + 4)
    s = store(tmp_path / "d.p4", data[: BASIS_FROM - 1])
    crcs = array("I", s.crcs)
    s.close()
    s = DenseStore(tmp_path / "d.p4", SHAPE, crcs, codec="p4")
    for t in data[BASIS_FROM - 1 :]:
        s.append(np.ascontiguousarray(t))
    assert s.basis.start == BASIS_FROM and s.basis.recoded == []
    got = s.read(np.arange(len(data)))
    for i in range(BASIS_FROM):
        np.testing.assert_array_equal(got[i], q4(data[i]))
    assert not np.array_equal(got[BASIS_FROM], q4(data[BASIS_FROM]))
    s.close()


def test_entries_before_the_basis_are_coded_with_it_too(tmp_path: Path) -> None:
    data = tokens(1, BASIS_FROM + 8)
    s = store(tmp_path / "d.p4", data)
    assert s.basis is not None and s.basis.start == BASIS_FROM
    assert len(s.basis.recoded) == BASIS_FROM  # in their slots: no copies
    assert (tmp_path / "d.p4").stat().st_size == head_bytes(SHAPE, "p4") + len(data) * (
        entry_bytes(SHAPE, "p4")
    )
    err = s.read(np.arange(len(data))).astype(np.float32) - data.astype(np.float32)
    q4_err = np.stack([q4(t) for t in data]).astype(np.float32) - data.astype(np.float32)
    per_entry = (err**2).mean((1, 2)) / (q4_err**2).mean((1, 2))
    assert per_entry.max() < 0.05, per_entry  # every entry (measured 0.004 at most)
    s.close()


def test_error_the_decoder_sees_is_smaller_than_q4s(tmp_path: Path) -> None:
    """The error W e that moves a pair score: p4 (fitted for W) against q4, same bytes."""
    data, w = tokens(2, BASIS_FROM + 12), weight()
    s = store(tmp_path / "d.p4", data, w)
    later = data[BASIS_FROM:].astype(np.float32)
    p4_err = s.read(np.arange(BASIS_FROM, len(data))).astype(np.float32) - later
    q4_err = np.stack([q4(t) for t in data[BASIS_FROM:]]).astype(np.float32) - later
    ratio = ((p4_err @ w.T) ** 2).mean() / ((q4_err @ w.T) ** 2).mean()
    assert ratio < 0.05, ratio  # measured 0.003
    s.close()


def _meta(i: int) -> KeyframeMeta:
    return KeyframeMeta(stamp=100.0 + i, frame_id="cam", source="s")


def _desc(i: int) -> np.ndarray:
    v = np.random.default_rng(i).normal(size=DIM).astype(np.float32)
    return v / np.linalg.norm(v)


def _map(path: Path, data: np.ndarray, w=None, first: int = 0) -> Path:
    with PlaceMap(DIM, SHAPE, "fp", P4, dense_weight=w) as m:
        for i, t in enumerate(data):
            m.add(_desc(first + i), t, _meta(first + i))
        m.save(path)
    return path


@pytest.mark.parametrize("first", [BASIS_FROM - 4, BASIS_FROM + 4])
def test_a_reloaded_map_gives_the_same_tokens_and_continues(tmp_path: Path, first: int) -> None:
    """Saved before or after the basis was fitted, reloaded, continued, reloaded again."""
    data = tokens(3, BASIS_FROM + 10)
    with PlaceMap(DIM, SHAPE, "fp", P4) as m:
        for i in range(first):
            m.add(_desc(i), data[i], _meta(i))
        m.save(tmp_path / "m")
        before = m.get_dense(range(first))
    with PlaceMap.load(tmp_path / "m") as m:
        np.testing.assert_array_equal(m.get_dense(range(first)), before)
        for i in range(first, len(data)):
            m.add(_desc(i), data[i], _meta(i))
        m.save(tmp_path / "m")
        everything = m.get_dense(range(len(data)))
        assert m.dense_basis is not None
    with PlaceMap.load(tmp_path / "m", verify_dense=True) as m:
        np.testing.assert_array_equal(m.get_dense(range(len(data))), everything)
        assert m.index_config.dense_codec == "p4" and m.dense_basis.start == BASIS_FROM


def test_a_map_saved_before_the_fit_codes_its_first_entries_at_the_next_save(tmp_path):
    """Issue 48, loose end 5: saved at 12 keyframes, the basis fitted at the 17th: the next save
    writes a new generation whose dense copy codes the first 16 with the basis too (their
    float16 tokens were kept for it); the later entries keep their bytes, their CRC32s (seeded
    by the basis's, which now lists the first 16's) follow in the new store's rows."""
    data, d = tokens(6, BASIS_FROM + 6), tmp_path / "m"
    with PlaceMap(DIM, SHAPE, "fp", P4) as m:
        for i in range(12):
            m.add(_desc(i), data[i], _meta(i))
        m.save(d)
        for i in range(12, len(data)):
            m.add(_desc(i), data[i], _meta(i))
        assert m._dense.recode_pending and m.dense_basis.recoded == []
        later = m.get_dense(range(BASIS_FROM, len(data)))
        m.save(d)
        assert not m._dense.recode_pending and len(m.dense_basis.recoded) == BASIS_FROM
        assert sorted(p.name for p in d.glob("dense-*")) == ["dense-2.p4"]  # a new generation
    with PlaceMap.load(d, verify_dense=True) as m:
        basis, size = m.dense_basis, entry_bytes(SHAPE, "p4")
        first = np.stack([basis.decode(basis.encode(t, size), SHAPE[0]) for t in data[:16]])
        np.testing.assert_array_equal(m.get_dense(range(BASIS_FROM)), first)
        np.testing.assert_array_equal(m.get_dense(range(BASIS_FROM, len(data))), later)
        q4_err = np.abs(np.stack([q4(t) for t in data[:16]]) - data[:16]).mean()
        assert np.abs(first.astype(np.float32) - data[:16]).mean() < q4_err


def test_merge_and_compact_recode_into_one_basis(tmp_path: Path) -> None:
    """Two maps with their own bases merged: the first's basis codes every merged entry (from
    entry 0); each comes back near its input's decoded tokens; compact keeps the basis."""
    a = _map(tmp_path / "a", tokens(4, BASIS_FROM + 4), weight())
    b = _map(tmp_path / "b", tokens(5, BASIS_FROM + 2), None, first=100)
    with PlaceMap.load(a, read_only=True) as ma, PlaceMap.load(b, read_only=True) as mb:
        inputs = np.concatenate([ma.get_dense(range(len(ma))), mb.get_dense(range(len(mb)))])
        basis_a, basis_b = ma.dense_basis, mb.dense_basis
    assert not np.array_equal(basis_a.enc16, basis_b.enc16)
    merge_maps([a, b], tmp_path / "ab")
    compact_map(tmp_path / "ab", tmp_path / "abc", codec="p4", policy=False)
    for out in ("ab", "abc"):
        with PlaceMap.load(tmp_path / out, read_only=True) as m:
            assert m.dense_basis.start == 0
            np.testing.assert_array_equal(m.dense_basis.enc16, basis_a.enc16)
            got = m.get_dense(range(len(m))).astype(np.float32)
            assert np.abs(got - inputs).max() < 0.1 * np.abs(inputs).max()


def test_each_component_gets_the_grid_of_least_error() -> None:
    """The encoder's grid clips a bell-shaped component's tails where that removes error (few
    bits), never giving more error than its full range (min to max) on the tokens it weighs."""
    y = np.random.default_rng(0).normal(size=(128, 6)).astype(np.float32)
    levels = np.array([1, 1, 3, 3, 15, 255], np.float32)

    def error(lo: np.ndarray, step: np.ndarray) -> np.ndarray:  # as the decoder rebuilds y
        s, low = step.astype(np.float32), lo.astype(np.float32)
        q = np.clip(np.rint((y - low) / s), 0, levels)
        return np.square(q * s + low - y).sum(0)

    full_lo = _toward(y.min(0), down=True)
    full = error(full_lo, _toward((y.max(0) - full_lo.astype(np.float32)) / levels, down=False))
    got = error(*_grid(y, levels))
    assert (got <= full).all()
    assert got[:4].sum() < 0.5 * full[:4].sum()  # 1 and 2 bits: far less error
