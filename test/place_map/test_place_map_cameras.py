"""The rig camera of each keyframe (issue 49): stored, saved, loaded, merged; maps saved before
the camera column read as camera 0 and take keyframes of other cameras; a camera-0 row is
written exactly as before the column (same CRC32); bad values are refused, damaged ones found."""

from __future__ import annotations

import shutil
import sqlite3
from dataclasses import replace
from pathlib import Path

import pytest
from test_bad_input_map import MAPS
from test_place_map_persist import DIM, SHAPE, add_range, dense_for, desc_for, meta_for

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.merge import merge_maps
from pair_vpr_ros.place_map.store import row_crc


def _sqlite(d: Path) -> Path:
    return next(d.glob("map-*.sqlite"))


def _add(m: PlaceMap, i: int, camera: int) -> int:
    return m.add(desc_for(i), dense_for(i), replace(meta_for(i), camera=camera))


def test_cameras_round_trip_and_camera_0_rows_keep_their_old_crc(tmp_path: Path) -> None:
    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        for i in range(6):
            _add(m, i, i % 3)
        m.save(tmp_path / "map")
    with PlaceMap.load(tmp_path / "map") as m:
        assert [m.meta(i).camera for i in range(6)] == [0, 1, 2, 0, 1, 2]
        assert [k.camera for k in m.all_meta()] == [0, 1, 2, 0, 1, 2]
    with sqlite3.connect(_sqlite(tmp_path / "map")) as db:
        rows = db.execute(
            "SELECT id, stamp, frame_id, source, x, y, z, qx, qy, qz, qw, robot, session, "
            "descriptor, dense_crc, crc, camera FROM keyframes ORDER BY id"
        ).fetchall()
    for row in rows:  # a camera-0 row: the CRC32 of the row as it was before the column
        assert row[15] == row_crc(row[:15], row[16])
        assert (row[15] == row_crc(row[:15])) == (row[16] == 0)


def test_a_map_saved_before_the_camera_column_reads_camera_0_and_grows(tmp_path: Path) -> None:
    d = Path(shutil.copytree(MAPS / "format-3", tmp_path / "map"))
    with sqlite3.connect(_sqlite(d)) as db:
        columns = [r[1] for r in db.execute("PRAGMA table_info(keyframes)")]
    assert "camera" not in columns  # the fixture was written before issue 49
    with PlaceMap.load(d, read_only=True) as m:  # read as it is: camera 0, nothing written
        assert {k.camera for k in m.all_meta()} == {0} and m.meta(0).camera == 0
    with PlaceMap.load(d) as m:  # opened for writing: schema version 2 (place_map/schema.py)
        n = len(m)
        assert {k.camera for k in m.all_meta()} == {0}
        assert _add(m, 100, 1) == n and _add(m, 101, 0) == n + 1
        m.save(d)
    with PlaceMap.load(d) as m:
        assert [m.meta(i).camera for i in range(n + 2)] == [0] * n + [1, 0]
        assert m.meta(n).stamp == meta_for(100).stamp


def test_merge_keeps_each_keyframes_camera(tmp_path: Path) -> None:
    for name, cameras in (("a", [0, 1]), ("b", [1, 0, 1])):
        with PlaceMap(DIM, SHAPE, "fp-a") as m:
            for i, cam in enumerate(cameras):
                m.add(desc_for(i), dense_for(i), KeyframeMeta(stamp=i, robot=name, camera=cam))
            m.save(tmp_path / name)
    merge_maps([tmp_path / "a", tmp_path / "b"], tmp_path / "merged")
    with PlaceMap.load(tmp_path / "merged") as m:
        assert [(k.robot, k.camera) for k in m.all_meta()] == [
            ("a", 0), ("a", 1), ("b", 1), ("b", 0), ("b", 1)]  # fmt: skip


@pytest.mark.parametrize("camera", [-1, 1.5, "1", True, 2**31])
def test_a_bad_camera_is_refused_and_nothing_is_stored(camera) -> None:
    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        with pytest.raises(MapError, match="keyframe camera must be a rig camera index >= 0"):
            m.add(desc_for(0), dense_for(0), KeyframeMeta(stamp=1.0, camera=camera))
        assert len(m) == 0


def test_a_changed_camera_fails_the_row_crc(tmp_path: Path) -> None:
    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        add_range(m, 0, 3)
        _add(m, 3, 1)
        m.save(tmp_path / "map")
    with sqlite3.connect(_sqlite(tmp_path / "map")) as db:
        db.execute("UPDATE keyframes SET camera = 2 WHERE id = 3")
    with PlaceMap.load(tmp_path / "map") as m:
        with pytest.raises(MapError, match="keyframe 3 with a wrong CRC32"):
            m.meta(3)
