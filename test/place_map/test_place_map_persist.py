"""PlaceMap save/load: round trips, continued mapping, save-as, locking, fingerprint, damage."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from pair_vpr_ros.errors import MapError, MapFingerprintError
from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.dense_codec import Basis, decode, encode, entry_bytes, head_bytes

DIM, SHAPE, N0 = 8, (4, 8), 12
CODEC = IndexConfig().dense_codec  # the default: these maps are made with it
ENTRY, HEAD = entry_bytes(SHAPE, CODEC), head_bytes(SHAPE, CODEC)


def desc_for(i: int) -> np.ndarray:
    v = np.random.default_rng(1000 + i).normal(size=DIM).astype(np.float32)
    return v / np.linalg.norm(v)


def dense_for(i: int) -> np.ndarray:
    return np.arange(32, dtype=np.float32).reshape(SHAPE) * 0.25 + i


def stored(tokens: np.ndarray, codec: str = CODEC, basis: Basis | None = None) -> np.ndarray:
    """What a map of `codec` gives back for `tokens` (q4: the 4-bit decoded values; p4: coded
    with the map's `basis`, q4 in an entry without it)."""
    t = tokens.astype(np.float16)
    if codec == "p4" and basis is not None:
        return basis.decode(basis.encode(t, entry_bytes(t.shape, "p4")), t.shape[0])
    codec = "q4" if codec == "p4" else codec
    return decode(encode(t, codec), t.shape, codec)


def meta_for(i: int) -> KeyframeMeta:
    pose = (float(i), 0.5, -1.0, 0.0, 0.0, 0.0, 1.0) if i % 2 else None
    return KeyframeMeta(stamp=100.0 + i, frame_id=f"cam{i % 3}", pose=pose, source="s1")


def features_for(i: int) -> bytes:
    """Packed keyframe features (opaque to the map); every third keyframe has none."""
    return b"" if i % 3 == 0 else np.random.default_rng(i).bytes(100 + 7 * i)


def add_range(m: PlaceMap, start: int, stop: int) -> None:
    for i in range(start, stop):
        assert m.add(desc_for(i), dense_for(i), meta_for(i), features_for(i)) == i


def assert_holds(m: PlaceMap, ids: list[int], codec: str = CODEC) -> None:
    """The map holds exactly keyframes `ids` (content of keyframe i = *_for(ids[i]))."""
    assert len(m) == len(ids)
    basis = m.dense_basis if codec == "p4" else None
    for kf_id, i in enumerate(ids):
        coded = basis is not None and not len(basis.recoded) <= kf_id < basis.start
        expect = stored(dense_for(i), codec, basis if coded else None)
        np.testing.assert_array_equal(m.get_dense([kf_id])[0], expect)
        np.testing.assert_allclose(m.get_desc([kf_id])[0], desc_for(i), atol=1e-6)
        assert m.meta(kf_id) == KeyframeMeta(kf_id, *list(meta_for(i).__dict__.values())[1:])
        assert m.features(kf_id) == features_for(i)


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        add_range(m, 0, N0)
        m.save(tmp_path / "map")
    return tmp_path / "map"


def files(d: Path) -> list[str]:
    return sorted(os.listdir(d))


@pytest.mark.parametrize(
    "index",
    ["flat", IndexConfig(kind="hnsw", exact_below=0), IndexConfig(kind="ivf", train_at=39)],
)
def test_save_load_gives_identical_results(tmp_path: Path, index) -> None:
    queries = [desc_for(i) + 0.3 * desc_for(i + 50) for i in range(8)]
    with PlaceMap(DIM, SHAPE, "fp-a", index=index) as m:
        add_range(m, 0, 40)
        before = [m.search(q, 5, max_id=30) for q in queries]
        m.save(tmp_path / "map")
    with PlaceMap.load(tmp_path / "map", expected_fingerprint="fp-a") as m:
        assert [m.search(q, 5, max_id=30) for q in queries] == before
        assert m.index_config == (index if isinstance(index, IndexConfig) else IndexConfig())
        assert m.fingerprint == "fp-a" and m.dense_shape == SHAPE and m.desc_dim == DIM
        assert_holds(m, list(range(40)))


def test_empty_map_round_trip(tmp_path: Path) -> None:
    with PlaceMap(DIM, SHAPE, "fp-a", index="hnsw") as m:
        m.save(tmp_path / "empty")
    with PlaceMap.load(tmp_path / "empty", verify_dense=True) as m:
        assert len(m) == 0 and m.search(desc_for(0), 3) == [] and m.all_meta() == []
        assert m.index_config.kind == "hnsw"
        add_range(m, 0, 2)
        m.save(tmp_path / "empty")
    with PlaceMap.load(tmp_path / "empty", read_only=True) as m:
        assert_holds(m, [0, 1])


def test_continue_after_load_and_save_to_same_dir(saved: Path) -> None:
    layout = [f"dense-1.{CODEC}", "manifest.json", "map-1.sqlite", "map-1.sqlite.desc", "map.lock"]
    assert files(saved) == layout
    manifest = (saved / "manifest.json").read_bytes()
    with PlaceMap.load(saved) as m:
        add_range(m, N0, N0 + 3)
        m.save(saved)
        add_range(m, N0 + 3, N0 + 4)
        m.save(saved)
    # Incremental saves: the dense file is appended, the store takes the new rows, the manifest
    # is written again as the record of the save (its count; the rest as it was).
    record = json.loads((saved / "manifest.json").read_text())
    first = json.loads(manifest)
    assert files(saved) == layout and (first["count"], record["count"]) == (N0, N0 + 4)
    assert {k: v for k, v in record.items() if k not in ("count", "checksum")} == {
        k: v for k, v in first.items() if k not in ("count", "checksum")
    }
    assert (saved / f"dense-1.{CODEC}").stat().st_size == HEAD + (N0 + 4) * ENTRY
    with PlaceMap.load(saved) as m:
        assert_holds(m, list(range(N0 + 4)))


def test_unsaved_changes_never_reach_the_saved_copy(saved: Path) -> None:
    with PlaceMap.load(saved) as m:
        add_range(m, N0, N0 + 5)
        m.clear()
        add_range(m, 0, 1)
    with PlaceMap.load(saved) as m:
        assert_holds(m, list(range(N0)))
        add_range(m, N0, N0 + 1)  # appends over the unsaved tail of the last session
        m.save(saved)
    with PlaceMap.load(saved) as m:
        assert_holds(m, list(range(N0 + 1)))


def test_save_after_clear_replaces_the_dense_file(saved: Path) -> None:
    with PlaceMap.load(saved) as m:
        m.clear()
        assert m.add(desc_for(7), dense_for(7), meta_for(7)) == 0
        m.save(saved)
    assert files(saved) == [
        f"dense-2.{CODEC}",
        "manifest.json",
        "map-2.sqlite",
        "map-2.sqlite.desc",
        "map.lock",
    ]
    with PlaceMap.load(saved) as m:
        assert len(m) == 1
        np.testing.assert_array_equal(m.get_dense([0])[0], stored(dense_for(7)))


def test_save_as_leaves_the_original_untouched(saved: Path, tmp_path: Path) -> None:
    other = tmp_path / "copy"
    with PlaceMap.load(saved) as m:
        add_range(m, N0, N0 + 2)
        assert m.save(other) == other.resolve() and m.directory == other.resolve()
        with PlaceMap.load(saved) as original:  # the old directory is no longer locked
            assert_holds(original, list(range(N0)))
        add_range(m, N0 + 2, N0 + 3)
        m.save(other)
    with PlaceMap.load(other) as m:
        assert_holds(m, list(range(N0 + 3)))
    with PlaceMap.load(saved) as m:
        assert_holds(m, list(range(N0)))


def test_fresh_map_saved_over_an_existing_map(saved: Path) -> None:
    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        assert [m.add(desc_for(i), dense_for(i), meta_for(i)) for i in (5, 6)] == [0, 1]
        m.save(saved)
    with PlaceMap.load(saved) as m:
        assert len(m) == 2
        np.testing.assert_array_equal(m.get_dense([1])[0], stored(dense_for(6)))
    assert files(saved) == [
        f"dense-2.{CODEC}",
        "manifest.json",
        "map-2.sqlite",
        "map-2.sqlite.desc",
        "map.lock",
    ]


def test_one_writer_per_directory_and_read_only_readers(saved: Path) -> None:
    with PlaceMap.load(saved) as writer:
        with pytest.raises(MapError, match=r"is open for writing by another PlaceMap \(pid \d+\)"):
            PlaceMap.load(saved)
        with PlaceMap(DIM, SHAPE, "fp-a") as fresh:
            with pytest.raises(MapError, match="open for writing by another PlaceMap"):
                fresh.save(saved)
        with PlaceMap.load(saved, read_only=True) as reader:
            assert_holds(reader, list(range(N0)))
            with pytest.raises(MapError, match="cannot add to a map loaded with read_only=True"):
                reader.add(desc_for(0), dense_for(0), meta_for(0))
        add_range(writer, N0, N0 + 1)
    PlaceMap.load(saved).close()  # closing released the lock


def test_fingerprint_mismatch_is_refused(saved: Path) -> None:
    with pytest.raises(
        MapFingerprintError,
        match="was built with model fingerprint 'fp-a', but the current model's fingerprint is "
        "'fp-b': load it with the same weights and image size",
    ):
        PlaceMap.load(saved, expected_fingerprint="fp-b")
    PlaceMap.load(saved, expected_fingerprint="fp-a").close()  # and the lock was released


def flip_byte(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    path.write_bytes(bytes(data))


def test_missing_directory(tmp_path: Path) -> None:
    with pytest.raises(MapError, match=r"nowhere/manifest.json is missing: .* is not a saved"):
        PlaceMap.load(tmp_path / "nowhere")
    assert not (tmp_path / "nowhere").exists()


def test_damaged_dense_entry_is_detected_by_crc(saved: Path) -> None:
    flip_byte(saved / f"dense-1.{CODEC}", HEAD + 5 * ENTRY + 3)  # inside keyframe 5
    with PlaceMap.load(saved) as m:
        np.testing.assert_array_equal(m.get_dense([4])[0], stored(dense_for(4)))
        with pytest.raises(MapError, match=rf"keyframe 5 in .*dense-1.{CODEC} fail their CRC32"):
            m.get_dense([4, 5])
    with pytest.raises(MapError, match="keyframe 5 .* fail their CRC32 check"):
        PlaceMap.load(saved, verify_dense=True)
    with PlaceMap.load(saved, verify_dense_reads=False) as m:  # documented: unchecked reads
        assert m.get_dense([5]).shape == (1, *SHAPE)
