"""fleet_peer_search "milvus": two robots' pipelines write one Milvus collection (a milvus-lite
file, then the test server) and each finds the other's keyframes there, under its own rules,
instead of broadcasting descriptors; the owner still scores with its own dense tokens. The
tiny random network: only exact repeats pass the global floor (exact_match.py)."""

from __future__ import annotations

from dataclasses import replace

import pytest
from exact_match import EXACT_MATCH

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.fleet import FleetConfig, FleetExchange, LocalBus
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.place_map.milvus.expr import ID_BITS
from pair_vpr_ros.place_map.milvus.peers import peer_expr

S1, S2 = "20261125T160000Z", "20261126T090000Z"


@pytest.fixture(scope="module")
def places():
    import numpy as np

    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(8)]


def robot(model, bus, name, session, index, folder=None):
    """Robot `name` on `bus`, its map in the shared collection (loaded from `folder`)."""
    pm = None
    if folder is not None and folder.is_dir():
        pm = PlaceMap.load(folder, model.fingerprint)
    pipe = LoopClosurePipeline(model, DetectorConfig(**EXACT_MATCH), place_map=pm, index=index,
                               identity=Identity(name, session))  # fmt: skip
    config = FleetConfig(robot=name, session=session, select="first", peer_search="milvus")
    ex = FleetExchange(pipe, config, bus.sender(name), first_request_id=0)
    bus.join(ex)
    return ex


def drive(bus, plan, places):
    """plan: [(robot exchange, place, stamp)] in stamp order -> loops decided."""
    loops = []
    for ex, place, stamp in plan:
        ex.on_keyframe(ex.pipe.process(Frame(stamp, places[place], frame_id="cam")))
        loops += bus.deliver()
    return loops


def keys(writers: list[int], counts: tuple[int, int]) -> list[int]:
    """The primary keys of keyframes 0..count-1 of each writer, sorted."""
    return sorted(w << ID_BITS | i for w, n in zip(writers, counts, strict=True) for i in range(n))


def rows(ex) -> list[int]:
    """Every primary key of the shared collection."""
    index = ex.pipe.place_map._index
    found = index.client.query(index.collection, filter="pk >= 0", output_fields=["pk"])
    return sorted(int(r["pk"]) for r in found)


def test_the_peer_filter_names_other_robots_only():
    assert peer_expr("a") == 'robot != "a"'
    assert peer_expr("a", ("b", "c")) == 'robot != "a" and robot in ["b", "c"]'


def test_two_robots_find_each_other_in_one_collection_and_after_a_restart(
    tiny_model, places, milvus, tmp_path
):
    # Strong: another writer's newest row is seen at once (Bounded: within ~5 s on a server)
    index = replace(milvus, milvus_consistency="Strong")
    bus = LocalBus()
    a = robot(tiny_model, bus, "a", S1, index)
    b = robot(tiny_model, bus, "b", S1, index)
    plan = [(a, 0, 0.0), (b, 4, 0.5), (a, 1, 1.0), (b, 5, 1.5), (b, 1, 3.5)]
    loops = drive(bus, plan, places)
    assert len(loops) == 1
    rec = loops[0].record
    assert (loops[0].query_robot, loops[0].match_robot) == ("b", "a")
    assert (rec.query_id, rec.match_id, rec.match_stamp, rec.accepted) == (2, 1, 1.0, True)
    assert (a.counts.loops_accepted, b.counts.loops_confirmed) == (1, 1)
    # nothing broadcast, nothing kept: the peers' rows were found in the collection
    assert a.counts.sent["keyframes"] == b.counts.sent["keyframes"] == 0
    assert len(b.store) == 0 and b.store.owners() == {f"a/{S1}": 1}
    assert not a.counts.skipped and not b.counts.skipped and b.store.skipped == 0
    writers = [ex.pipe.place_map._index.writer for ex in (a, b)]
    assert rows(a) == keys(writers, (2, 3))
    for ex, name in ((a, "a"), (b, "b")):
        ex.pipe.place_map.save(tmp_path / name)
        ex.pipe.place_map.close()

    # both restart from their folders, in a new session: b sees the place a saw in the
    # first run; a scores its loaded keyframe of session S1
    bus = LocalBus()
    a = robot(tiny_model, bus, "a", S2, index, tmp_path / "a")
    b = robot(tiny_model, bus, "b", S2, index, tmp_path / "b")
    assert [ex.pipe.place_map._index.writer for ex in (a, b)] == writers
    loops = drive(bus, [(a, 2, 10.0), (b, 0, 10.5)], places)
    assert len(loops) == 1 and loops[0].record.accepted
    assert (loops[0].record.match_id, loops[0].match_session) == (0, S1)
    assert (loops[0].query_session, loops[0].record.query_id) == (S2, 3)
    # every keyframe of both robots is in the collection once, under its map's writer key
    assert rows(a) == keys(writers, (3, 4))

    # a row the owner no longer has (a restarted without its folder: a new map, a new key)
    # costs one refused request, never a wrong loop
    a.pipe.place_map.close()
    bus = LocalBus()
    a2 = robot(tiny_model, bus, "a", S2, index)
    bus.join(b)
    b.send = bus.sender("b")
    assert drive(bus, [(b, 1, 20.0)], places) == []
    assert a2.counts.skipped == {"stale keyframe": 1}
    for ex in (a2, b):
        ex.pipe.place_map.close()


def test_milvus_peer_search_needs_a_milvus_map(tiny_model):
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT_MATCH))
    config = FleetConfig(robot="a", session=S1, peer_search="milvus")
    with pytest.raises(ConfigError) as err:
        FleetExchange(pipe, config, LocalBus().sender("a"))
    assert str(err.value) == (
        "fleet_peer_search milvus searches the Milvus collection the robots' maps share, but "
        "robot 'a''s place map is of index kind 'flat': set index to milvus with one milvus_uri "
        "and milvus_collection for every robot, or fleet_peer_search to broadcast"
    )
    pipe.place_map.close()
