"""Bad-input matrix, place-map index settings and "ivf" index files: every bad IndexConfig value
is a ConfigError naming the field; every IVF file that is not what the manifest says is a
MapError naming the file, and the load changes nothing."""

from __future__ import annotations

import math
from pathlib import Path

import faiss
import numpy as np
import pytest
from bad_input import tree_digest
from test_bad_input_map import _faiss, _rewrite_manifest, saved  # noqa: F401
from test_bad_input_map_store import faiss_snapshot, replace_snapshot, resign_manifest
from test_place_map_persist import DIM, SHAPE, add_range

from pair_vpr_ros.errors import ConfigError, MapError
from pair_vpr_ros.place_map import IndexConfig, PlaceMap

N_IVF = 60  # trained at 39 (train_at), not again before 156
IVF = IndexConfig(kind="ivf", train_at=39)

BAD_CONFIGS = {
    "kind": (dict(kind="pq"), r"must be one of \('flat', 'hnsw', 'ivf', 'milvus'\)"),
    "nlist negative": (dict(nlist=-1), r"IndexConfig.nlist must be an integer >= 0, got -1"),
    "nprobe zero": (dict(nprobe=0), r"IndexConfig.nprobe must be an integer >= 1, got 0"),
    "nprobe float": (dict(nprobe=2.5), r"nprobe must be an integer >= 1, got 2.5"),
    "nprobe text": (dict(nprobe="8"), r"nprobe must be an integer >= 1, got '8'"),
    "nprobe bool": (dict(nprobe=True), r"nprobe must be an integer >= 1, got True"),
    "train_at below 39": (dict(train_at=38), r"train_at must be an integer >= 39, got 38"),
    "ef_search zero": (dict(ef_search=0), r"ef_search must be an integer >= 1, got 0"),
    "growth 1": (dict(retrain_growth=1.0), r"retrain_growth must be a number > 1 .* got 1.0"),
    "growth below 1": (dict(retrain_growth=0.5), r"retrain_growth .* or 0 \(never .*got 0.5"),
    "growth negative": (dict(retrain_growth=-4), r"retrain_growth must be .* got -4"),
    "growth nan": (dict(retrain_growth=math.nan), r"retrain_growth must be .* got nan"),
    "growth inf": (dict(retrain_growth=math.inf), r"retrain_growth must be .* got inf"),
    "growth text": (dict(retrain_growth="4"), r"retrain_growth must be .* got '4'"),
}


@pytest.mark.parametrize("case", list(BAD_CONFIGS))
def test_bad_index_config_is_a_config_error(case: str) -> None:
    fields, message = BAD_CONFIGS[case]
    with pytest.raises(ConfigError, match=message):
        IndexConfig(**{"kind": "ivf", **fields})
    with pytest.raises(ConfigError, match=message):
        PlaceMap(DIM, SHAPE, "fp", index=IndexConfig(**{"kind": "ivf", **fields}))


def test_good_edge_values_are_accepted() -> None:
    IndexConfig(kind="ivf", nlist=0, nprobe=1, train_at=39, retrain_growth=0)
    IndexConfig(kind="ivf", nlist=np.int64(5), retrain_growth=1.5)  # numpy integers are fine


@pytest.fixture
def saved_ivf(tmp_path: Path) -> Path:
    with PlaceMap(DIM, SHAPE, "fp-a", index=IVF) as m:
        add_range(m, 0, N_IVF)
        assert isinstance(m._index._index, faiss.IndexIVFFlat)
        m.save(tmp_path / "map")
    return tmp_path / "map"


def _ivf(count: int, metric=faiss.METRIC_INNER_PRODUCT, ids=None, train=True) -> faiss.Index:
    """An IVF-Flat index of 4 lists over `count` random unit vectors."""
    quantizer = faiss.IndexFlatIP(DIM) if metric == faiss.METRIC_INNER_PRODUCT else None
    index = faiss.IndexIVFFlat(quantizer or faiss.IndexFlatL2(DIM), DIM, 4, metric)
    x = np.random.default_rng(0).normal(size=(max(count, 200), DIM)).astype(np.float32)
    if train:
        index.train(x)
        index.add_with_ids(x[:count], np.arange(count) if ids is None else ids)
    return index


IVF_CORRUPTIONS = {
    "settings nprobe zero": (
        lambda d: resign_manifest(d, lambda m: m["index"].update(nprobe=0)),
        r"manifest index settings .* are invalid .*nprobe must be an integer >= 1, got 0",
    ),
    "settings growth text": (
        lambda d: resign_manifest(d, lambda m: m["index"].update(retrain_growth="x")),
        r"manifest index settings .* are invalid .*retrain_growth must be",
    ),
    "hnsw file": (
        lambda d: faiss_snapshot(d, faiss.IndexHNSWFlat(DIM, 4, faiss.METRIC_INNER_PRODUCT)),
        r"is a IndexHNSWFlat of dim 8, but the manifest says 'ivf' of dim 8",
    ),
    "ivf of another dim": (
        lambda d: faiss_snapshot(d, faiss.IndexIVFFlat(faiss.IndexFlatIP(9), 9, 2, 0)),
        r"is a IndexIVFFlat of dim 9, but the manifest says 'ivf' of dim 8",
    ),
    "ivf l2": (
        lambda d: faiss_snapshot(d, _ivf(N_IVF, faiss.METRIC_L2)),
        r"does not use inner product",
    ),
    "ivf untrained": (
        lambda d: faiss_snapshot(d, _ivf(0, train=False)),
        r"is an untrained or inconsistent IVF index \(4 lists, quantizer IndexFlatIP of 0\)",
    ),
    "ivf other ids": (
        lambda d: faiss_snapshot(d, _ivf(N_IVF, ids=np.arange(N_IVF) + 100)),
        r"holds ids other than 0..59: the map is damaged",
    ),
    "ivf fewer vectors": (
        lambda d: faiss_snapshot(d, _ivf(30)),
        r"index-1-0.faiss holds 30 vectors, the map lists 60 keyframes",
    ),
    "ivf truncated": (
        lambda d: replace_snapshot(d, (d / "index-1-0.faiss").read_bytes()[:-300]),
        r"index-1-0.faiss could not be read",
    ),
}


@pytest.mark.parametrize("case", list(IVF_CORRUPTIONS))
def test_damaged_ivf_map_gives_map_error_and_stays_unchanged(saved_ivf: Path, case) -> None:
    damage, message = IVF_CORRUPTIONS[case]
    damage(saved_ivf)
    before = tree_digest(saved_ivf)
    with pytest.raises(MapError, match=message):
        PlaceMap.load(saved_ivf)
    with pytest.raises(MapError, match=message):
        PlaceMap.load(saved_ivf, read_only=True)
    assert tree_digest(saved_ivf) == before


def test_ivf_file_in_a_flat_map_is_refused(saved: Path) -> None:  # noqa: F811
    _faiss(saved, _ivf(12))
    with pytest.raises(
        MapError, match=r"is a IndexIVFFlat of dim 8, but the manifest says 'flat'"
    ):
        PlaceMap.load(saved)


def test_map_saved_before_ivf_existed_loads_with_defaults(saved: Path) -> None:  # noqa: F811
    """Manifests written before the ivf fields existed hold none of them: defaults apply."""
    _rewrite_manifest(
        saved,
        lambda m: [m["index"].pop(f) for f in ("nlist", "nprobe", "train_at", "retrain_growth")],
    )
    with PlaceMap.load(saved) as m:
        assert m.index_config == IndexConfig(dense_codec="f16") and len(m) == 12
