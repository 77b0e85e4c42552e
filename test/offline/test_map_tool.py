"""`pairvpr-map`: info and merge of saved place maps (issue 22 part 3)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
from bad_input import saved_map_digest
from map_fixtures import make_map

from pair_vpr_ros.offline.map_cli import main
from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.place_map.info import map_info
from pair_vpr_ros.place_map.merge import merge_maps


def test_info_reports_sessions_model_index_and_sizes(tmp_path, capsys):
    a = make_map(tmp_path / "a", "r1", "mon", 3, seed=1)
    info = map_info(a)
    assert (info.keyframes, info.fingerprint, info.index["kind"], info.format_version) == (
        3, "model-a", "flat", 4,
    )  # fmt: skip
    assert [(s.robot, s.session, s.keyframes, s.first_id, s.last_id) for s in info.sessions] == [
        ("r1", "mon", 3, 0, 2)
    ]
    on_disk = {p.name: p.stat().st_size for p in a.iterdir() if p.name != "map.lock"}
    assert info.files == on_disk and info.total_bytes == sum(on_disk.values())
    assert info.with_features == 1
    assert main(["info", str(a)]) == 0
    text = capsys.readouterr().out
    assert "keyframes: 3 stored (1 with features, 0 with an appearance signature), 0 " in text
    assert "  r1/mon: 3 (0..2, 10.000..12.000)" in text
    assert f"dense tokens: {list(info.dense_shape)} as p4\n" in text  # the default codec
    assert main(["info", str(a), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["total_bytes"] == info.total_bytes


def test_merge_renumbers_and_copies_everything_and_changes_no_input(tmp_path, capsys):
    a = make_map(tmp_path / "a", "r1", "mon", 3, seed=1)
    b = make_map(tmp_path / "b", "r2", "mon", 2, seed=2)
    before = {d: saved_map_digest(d) for d in (a, b)}
    assert main(["merge", str(a), str(b), "--out", str(tmp_path / "c"), "--quiet"]) == 0
    assert capsys.readouterr().out == (
        f"merged 5 keyframes of {a} (3), {b} (2) into {tmp_path / 'c'}\n"
    )
    with (
        PlaceMap.load(tmp_path / "c", read_only=True) as c,
        PlaceMap.load(a, read_only=True) as ma,
        PlaceMap.load(b, read_only=True) as mb,
    ):
        assert len(c) == 5 and [k.id for k in c.all_meta()] == list(range(5))
        for source, offset in ((ma, 0), (mb, 3)):
            for old in source.all_meta():
                new = c.meta(old.id + offset)
                assert new == replace(old, id=old.id + offset)
                np.testing.assert_array_equal(c.get_dense([new.id]), source.get_dense([old.id]))
                np.testing.assert_allclose(c.get_desc([new.id]), source.get_desc([old.id]), 1e-6)
                assert c.features(new.id) == source.features(old.id)
        assert c.search(mb.get_desc([1])[0], 1)[0][0] == 4
        assert c.fingerprint == "model-a"
    assert {d: saved_map_digest(d) for d in (a, b)} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b", "c"]  # no temporaries


def test_merge_keeps_a_shared_robot_session_with_a_warning(tmp_path, capsys):
    a = make_map(tmp_path / "a", "r1", "mon", 2, seed=1)
    b = make_map(tmp_path / "b", "r1", "mon", 2, seed=2)
    result = merge_maps([a, b], tmp_path / "c")
    assert result.keyframes == 4
    assert result.warnings == [
        f"robot 'r1' session 'mon' has keyframes in {a} and {b}: merged under one name (kept; a "
        "pose graph would take them for one trajectory)"
    ]
    assert main(["merge", str(a), str(b), "--out", str(tmp_path / "d"), "--quiet"]) == 0
    assert capsys.readouterr().err == f"warning: {result.warnings[0]}\n"
