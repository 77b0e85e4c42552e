"""Identity everywhere (issue 22 part 1): robot and session names, recency per robot-session,
identities in the map (old maps named at load) and in every loop record."""

from __future__ import annotations

import json
import shutil
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from exact_match import EXACT_MATCH

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.identity import Identity, resolve_identity, robot_from_namespace
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.recency import GroupedRecency, eligible_keyframes
from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.manifest import MANIFEST_NAME

MAPS = Path(__file__).parents[1] / "data" / "maps"  # maps written by earlier pair_vpr_ros


@pytest.mark.parametrize(
    "namespace,robot", [("/", "robot"), ("", "robot"), ("/r1", "r1"), ("/fleet/r1/", "fleet_r1")]
)
def test_robot_id_defaults_to_the_namespace_without_slashes(namespace, robot):
    assert robot_from_namespace(namespace) == robot


def test_session_id_defaults_to_the_start_time_utc():
    when = datetime(2026, 11, 25, 9, 30, 5, tzinfo=timezone.utc)
    assert resolve_identity("", "", "/r2", now=when) == Identity("r2", "20261125T093005Z")
    assert resolve_identity("a", "b", "/r2", now=when) == Identity("a", "b")


BAD_NAMES = ["my robot", "a/b", "", "x" * 65, "é", ".", "..", "a.b", "a@b", "a-b", "a,b",
             "loops.json", "fleet_summary.json", "x\n"]  # fmt: skip


@pytest.mark.parametrize("robot", [*BAD_NAMES, "1robot", "_r"])
def test_bad_robot_names_are_refused_with_the_rule(robot):
    """One rule (issue 38): a path component, a ROS topic token and a key everywhere."""
    with pytest.raises(ConfigError) as err:
        Identity(robot, "s1")
    assert str(err.value) == (
        f"robot_id {robot!r} must be 1-64 characters of ASCII letters, digits or '_' (a robot "
        "id starts with a letter): it names folders, a ROS topic and pose-graph keys, e.g. robot1"
    )


@pytest.mark.parametrize("session", BAD_NAMES)
def test_bad_session_names_are_refused_with_the_rule(session):
    with pytest.raises(ConfigError, match=r"^session_id .* e\.g\. 20261125T093000Z$"):
        Identity("r1", session)


@pytest.mark.parametrize("robot,session", [("r", "1"), ("R_2", "20261125T093000Z"),
                                           ("x" * 64, "_" * 64)])  # fmt: skip
def test_good_names_pass(robot, session):
    assert str(Identity(robot, session)) == f"{robot}/{session}"


# ---------------------------------------------------------------- recency per robot-session


def brute(keyframes, stamp, who, exclude_s, exclude_n):
    """Eligible ids by definition: another robot-session's at once; one's own as
    `eligible_keyframes` says over that robot-session's keyframes alone."""
    own = [k for k in keyframes if (k[2], k[3]) == who]
    mask = eligible_keyframes(np.array([k[1] for k in own]), stamp, exclude_s, exclude_n)
    allowed = {
        own[i][0] for i in range(len(own)) if mask is not None and i < len(mask) and mask[i]
    }
    return sorted(allowed | {k[0] for k in keyframes if (k[2], k[3]) != who})


def ids_of(result, n):
    if result is None:
        return []
    if result.prefix is not None:
        return list(range(result.prefix))
    if result.exclude is not None:
        lo, hi = result.exclude
        return [i for i in range(n) if not lo <= i < hi]
    return np.flatnonzero(result.mask).tolist()


@pytest.mark.parametrize("exclude_s,exclude_n", [(30.0, 0), (2.5, 3), (0.0, 1)])
def test_grouped_recency_equals_the_definition(exclude_s, exclude_n):
    rng = np.random.default_rng(7)
    groups = [("a", "s1"), ("a", "s2"), ("b", "s1")]
    for _ in range(300):
        keyframes, kf_id = [], 0
        for _ in range(rng.integers(1, 4)):  # sessions one after another, some interleaved
            who = groups[rng.integers(0, 3)]
            start = float(rng.integers(0, 50))
            for step in range(rng.integers(0, 12)):
                keyframes.append((kf_id, start + step * float(rng.integers(0, 3)), *who))
                kf_id += 1
        recency = GroupedRecency(keyframes)
        who = groups[rng.integers(0, 3)]
        stamp = float(rng.integers(-5, 80))
        got = recency.eligible(stamp, *who, exclude_s, exclude_n)
        want = brute(keyframes, stamp, who, exclude_s, exclude_n)
        assert ids_of(got, len(keyframes)) == want and (got is None) == (not want)
        assert got is None or got.count == len(want)


def test_a_live_session_after_a_loaded_map_is_one_prefix_and_others_at_once():
    old = [(i, float(i), "r", "old") for i in range(100)]  # same clock, same stamps
    live = [(100 + i, float(i), "r", "new") for i in range(50)]
    recency = GroupedRecency(old + live)
    got = recency.eligible(50.0, "r", "new", 30.0, 10)
    assert got.prefix == 121 and got.count == 121  # all of "old", "new" 0..20
    middle = recency.eligible(95.0, "r", "old", 30.0, 10)  # a session in the middle of the map
    assert middle.exclude == (66, 100) and middle.count == 150 - 34  # one range, no mask
    assert recency.sessions() == {("r", "old"): 100, ("r", "new"): 50}


# ---------------------------------------------------------------- pipeline and map


@pytest.fixture(scope="module")
def places():
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(6)]


def frames(places, order, t0=0.0):
    return [Frame(t0 + t, places[p], "cam") for t, p in enumerate(order)]


def accepted(outcomes):
    return [o.loop for o in outcomes if o.loop is not None and o.loop.accepted]


def test_a_map_recorded_on_an_overlapping_clock_keeps_its_candidates(tiny_model, places, tmp_path):
    config = DetectorConfig(**{**EXACT_MATCH, "exclude_recent_s": 30.0})
    first = LoopClosurePipeline(tiny_model, config, identity=Identity("r1", "monday"))
    list(first.process_many(frames(places, [0, 1, 2, 3])))
    first.save_map(tmp_path / "map")
    first.close()
    second = LoopClosurePipeline(tiny_model, config, identity=Identity("r1", "tuesday"))
    second.load_map(tmp_path / "map")
    loops = accepted(second.process_many(frames(places, [0, 1, 2, 3])))  # same stamps again
    assert [(r.query_id, r.match_id) for r in loops] == [(4, 0), (5, 1), (6, 2), (7, 3)]
    assert {(r.query_robot, r.query_session, r.match_robot, r.match_session) for r in loops} == {
        ("r1", "tuesday", "r1", "monday")
    }
    meta = second.place_map.meta(5)
    assert (meta.robot, meta.session) == ("r1", "tuesday")
    second.close()
    same = LoopClosurePipeline(tiny_model, config, identity=Identity("r1", "monday"))
    same.load_map(tmp_path / "map")  # the same session continued: excluded by stamp as before
    assert accepted(same.process_many(frames(places, [0, 1, 2, 3]))) == []
    same.close()


def test_an_old_map_loads_with_its_keyframes_named_and_a_note(tmp_path):
    shutil.copytree(MAPS / "format-1", tmp_path / "map")  # written before robots and sessions
    loaded = PlaceMap.load(tmp_path / "map", legacy_identity=("r7", "legacy"))
    assert [(k.robot, k.session) for k in loaded.all_meta()] == [("r7", "legacy")] * 12
    assert loaded.load_note == (
        f"place map {tmp_path / 'map'} is of format version 1; its 12 keyframes are named robot "
        "'r7', session 'legacy': loaded through a working copy, converted to format 4 by the "
        "next save into it (dense tokens stay float16)"
    )
    loaded.add(np.eye(8)[3], np.zeros((4, 8)), KeyframeMeta(stamp=9.0, robot="r7", session="s2"))
    loaded.save(tmp_path / "map")
    loaded.close()
    again = PlaceMap.load(tmp_path / "map", read_only=True)
    assert json.loads((tmp_path / "map" / MANIFEST_NAME).read_text())["format_version"] == 4
    assert [k.session for k in again.all_meta()] == ["legacy"] * 12 + ["s2"]
    assert not again.load_note
    again.close()


def test_search_can_exclude_one_id_range():
    m = PlaceMap(desc_dim=4, dense_shape=(1, 1))
    for i in range(8):
        m.add(np.array([1.0, 0.1 * i, 0, 0]), np.zeros((1, 1)), KeyframeMeta(stamp=float(i)))
    assert sorted(i for i, _ in m.search(np.array([1.0, 0, 0, 0]), 8, exclude=(2, 6))) == [
        0, 1, 6, 7,
    ]  # fmt: skip
    m.close()
