"""Fixtures of the "milvus" place-map tests, provided to every test by test/conftest.py: one
milvus-lite file per test module (its start takes ~1 s) and a fresh collection per test. Both
skip (fail under CI) where the milvus extra is not installed."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
from extras import require

from pair_vpr_ros.place_map import IndexConfig

_names = itertools.count()


@pytest.fixture(scope="module")
def lite_db(tmp_path_factory) -> Path:
    require("pymilvus")
    require("milvus_lite")
    return tmp_path_factory.mktemp("milvus") / "maps.db"


@pytest.fixture
def milvus(lite_db: Path) -> IndexConfig:
    """An IndexConfig of a collection no other test uses (exact FLAT: results comparable)."""
    name = f"kf_{next(_names)}"
    return IndexConfig(
        kind="milvus", milvus_uri=str(lite_db), milvus_collection=name, milvus_index="FLAT"
    )
