"""`pairvpr-bag-replay --index milvus` on a milvus-lite file and a server: the loops of the
default index, twice in a row against the same store (the second run starts clean: its own
writer key)."""

from __future__ import annotations

import json

import pytest
from bag_fixtures import revisit_world, write_rosbag2
from test_replay import CONFIG

from pair_vpr_ros.model import save_pairvpr
from pair_vpr_ros.offline.replay import cli as replay_cli
from pair_vpr_ros.offline.replay.cli import main
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag
from pair_vpr_ros.place_map import IndexConfig, PlaceMap


def _loops(out) -> list[tuple[int, int]]:
    return [(r["query_id"], r["match_id"]) for r in json.loads((out / "loops.json").read_text())]


@pytest.mark.slow  # three replays of the revisit bag
def test_replay_on_milvus_accepts_the_loops_of_the_default_index(tmp_path, tiny_model, milvus):
    images, poses = revisit_world()
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    runs = {}
    for name, index in (("flat", IndexConfig()), ("m1", milvus), ("m2", milvus)):
        options = ReplayOptions(progress=False, index=index)
        s = replay_bag(bag, tmp_path / name, options, model=tiny_model, config=CONFIG)
        assert s.error is None and s.pipeline_counts["map_searches_skipped"] == 0
        runs[name] = _loops(tmp_path / name)
    assert len(runs["flat"]) == 7 and runs["m1"] == runs["flat"] and runs["m2"] == runs["flat"]
    with PlaceMap.load(tmp_path / "m1" / "map", tiny_model.fingerprint) as first:
        with PlaceMap.load(tmp_path / "m2" / "map", tiny_model.fingerprint) as second:
            assert first._index.writer != second._index.writer
            assert len(first) == len(second) == 17


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory, tiny_model):
    return save_pairvpr(tiny_model, tmp_path_factory.mktemp("w") / "tiny.pth")


def test_cli_index_flags(tmp_path, tiny_weights, capsys, monkeypatch):
    """--index milvus needs --milvus-uri; the flags reach the replay as an IndexConfig."""
    bag = write_rosbag2(tmp_path / "bag", revisit_world()[0][:2])
    args = [str(bag), "--weights", str(tiny_weights), "--out", str(tmp_path / "o"), "--quiet"]
    assert main([*args, "--index", "milvus"]) == 1
    assert capsys.readouterr().err == (
        "error: milvus_uri must be a milvus-lite file (a path ending in .db) or a Milvus server "
        "address (http://host:19530), got ''\n"
    )
    seen = []
    monkeypatch.setattr(replay_cli, "replay_bag", lambda *a, **kw: seen.append(a[2]) or 1 / 0)
    db = tmp_path / "m.db"
    flags = ["--index", "milvus", "--milvus-uri", str(db), "--milvus-collection", "site_a"]
    try:
        main([*args, *flags, "--milvus-index", "IVF_FLAT"])
    except ZeroDivisionError:
        pass
    assert seen[0].index == IndexConfig(
        kind="milvus", milvus_uri=str(db), milvus_collection="site_a", milvus_index="IVF_FLAT"
    )
