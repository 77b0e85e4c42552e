"""Keyframe features in a saved place map: damaged or stray feature rows are MapErrors."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest
from test_place_map_persist import DIM, SHAPE, add_range, features_for

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.place_map.manifest import MANIFEST_NAME


def edit_meta(map_dir: Path, sql: str, *args) -> None:
    """Run `sql` on the saved keyframe store (as if the file came damaged that way)."""
    manifest = json.loads((map_dir / MANIFEST_NAME).read_text())
    conn = sqlite3.connect(map_dir / manifest["files"]["store"]["name"])
    with conn:
        conn.execute(sql, args)
    conn.close()


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        add_range(m, 0, 5)
        assert m.feature_stats() == (3, sum(len(features_for(i)) for i in range(5)))
        m.save(tmp_path / "map")
    return tmp_path / "map"


def test_a_flipped_feature_byte_is_a_map_error_on_read(saved: Path) -> None:
    edit_meta(saved, "UPDATE features SET data = ? WHERE id = 1", b"x" + features_for(1)[1:])
    with PlaceMap.load(saved) as m:
        assert m.features(2) == features_for(2)
        with pytest.raises(MapError, match="features of keyframe 1 fail their CRC32 check"):
            m.features(1)


def test_feature_rows_of_no_keyframe_are_refused_at_load(saved: Path) -> None:
    edit_meta(saved, "INSERT INTO features (id, crc, data) VALUES (9, 0, x'00')")
    with pytest.raises(MapError, match="holds 1 feature rows of no keyframe"):
        PlaceMap.load(saved)


def test_features_of_an_unknown_keyframe_is_a_map_error(saved: Path) -> None:
    with PlaceMap.load(saved) as m, pytest.raises(MapError, match="keyframe 7 is not in the map"):
        m.features(7)
