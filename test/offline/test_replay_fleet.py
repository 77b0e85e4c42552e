"""Replays with an identity (--robot-id, --session-id) and prior maps (--prior-map), issue 22."""

from __future__ import annotations

import csv
import json

import pytest
from bad_input import saved_map_digest
from bag_fixtures import revisit_world, write_rosbag2

from pair_vpr_ros.errors import ConfigError, MapError
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.model import save_pairvpr
from pair_vpr_ros.offline.replay.cli import main
from pair_vpr_ros.offline.replay.options import ReplayOptions
from pair_vpr_ros.offline.replay.run import replay_bag
from pair_vpr_ros.place_map import PlaceMap

CONFIG = DetectorConfig(
    top_k=1, score_threshold=-1e9, keyframe_max_similarity=1.0,
    exclude_recent_s=30.0, exclude_recent_keyframes=0,
)  # fmt: skip
WHO = ("query_robot", "query_session", "match_robot", "match_session")


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    images, poses = revisit_world()
    return write_rosbag2(tmp_path_factory.mktemp("bag") / "bag", images, poses)


@pytest.fixture(scope="module")
def first(bag, tmp_path_factory, tiny_model):
    """A replay of `bag` as robot r1, session mon: its out folder (map in out/map)."""
    out = tmp_path_factory.mktemp("first") / "out"
    options = ReplayOptions(progress=False, robot_id="r1", session_id="mon")
    summary = replay_bag(bag, out, options, model=tiny_model, config=CONFIG)
    assert summary.error is None
    return out


def test_identity_reaches_every_output(first):
    summary = json.loads((first / "summary.json").read_text())
    assert (summary["robot"], summary["session"]) == ("r1", "mon")
    assert summary["loops_by_match"] == {"r1/mon": 7} and summary["prior_maps"] == []
    loops = json.loads((first / "loops.json").read_text())
    assert {tuple(r[k] for k in WHO) for r in loops} == {("r1", "mon", "r1", "mon")}
    with open(first / "loops.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert {tuple(r[k] for k in WHO) for r in rows} == {("r1", "mon", "r1", "mon")}
    with PlaceMap.load(first / "map", read_only=True) as saved:
        assert {(m.robot, m.session) for m in saved.all_meta()} == {("r1", "mon")}


def test_a_prior_map_is_searched_at_once_and_never_written(bag, first, tmp_path, tiny_model):
    before = saved_map_digest(first / "map")
    options = ReplayOptions(
        progress=False, robot_id="r1", session_id="tue", prior_maps=(first / "map",)
    )
    config = CONFIG.updated(loop_per_map=False)  # one top-K of both maps, one loop a keyframe
    s = replay_bag(bag, tmp_path / "out", options, model=tiny_model, config=config)
    assert s.error is None and s.keyframes == 17
    # the same bag again: every frame finds itself in the prior map at once (same stamps: a
    # map recorded on an overlapping clock keeps its candidates); the 5 revisits see their
    # first visit in both maps, equally similar: the live map comes first on a tie
    assert s.loops == 17 and s.loops_by_match == {"r1/mon": 12, "r1/tue": 5}
    assert s.prior_maps == [
        {"dir": str((first / "map").resolve()), "keyframes": 17, "sessions": {"r1/mon": 17}}
    ]
    loops = json.loads((tmp_path / "out" / "loops.json").read_text())
    assert [(r["query_id"], r["match_id"], r["match_session"]) for r in loops[:3]] == [
        (0, 0, "mon"), (1, 1, "mon"), (2, 2, "mon"),
    ]  # fmt: skip
    ev = s.evaluation  # loops into the prior map are not this run's: unlabelled here ...
    assert (ev["accepted"], ev["unlabelled_accepted"], ev["true_accepted"]) == (17, 12, 5)
    prior = s.prior_evaluation  # ... and labelled apart: the prior map is of this very bag
    assert (prior["covered"], prior["prior_keyframes"], prior["positives"]) == (17, 17, 17)
    assert (prior["accepted"], prior["true_accepted"], prior["false_accepted"]) == (12, 12, 0)
    assert (prior["unlabelled_accepted"], prior["precision"]) == (0, 1.0)
    assert prior["recall"] == pytest.approx(12 / 17)
    assert s.line().startswith("frames 17, keyframes 17, loops 17 (5 live, 12 into prior maps)")
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["prior_evaluation"] == prior
    assert saved_map_digest(first / "map") == before
    with PlaceMap.load(tmp_path / "out" / "map", read_only=True) as live:
        assert len(live) == 17 and {m.session for m in live.all_meta()} == {"tue"}


def test_a_keyframe_closes_one_loop_into_each_map(bag, first, tmp_path, tiny_model):
    # loop_per_map (the default): each map gives its own top-K and at most one loop. Every
    # frame finds its own image in the prior map (17), and the live map gives the 7 loops the
    # first replay found within its own drive (threshold -1e9: every query with an eligible
    # keyframe, t >= 100 s): 24 loops, two for each of the 7 keyframes at t >= 100 s
    options = ReplayOptions(
        progress=False, robot_id="r1", session_id="tue", prior_maps=(first / "map",)
    )
    s = replay_bag(bag, tmp_path / "out", options, model=tiny_model, config=CONFIG)
    assert s.error is None and s.keyframes == 17
    assert s.loops == 24 and s.loops_by_match == {"r1/mon": 17, "r1/tue": 7}
    first_loops = json.loads((first / "loops.json").read_text())
    loops = json.loads((tmp_path / "out" / "loops.json").read_text())
    within = [(r["query_id"], r["match_id"]) for r in loops if r["match_session"] == "tue"]
    assert within == [(r["query_id"], r["match_id"]) for r in first_loops if r["accepted"]]
    into_prior = [(r["query_id"], r["match_id"]) for r in loops if r["match_session"] == "mon"]
    place = [*range(10), *range(5), 10, 11]  # revisit_world: keyframe -> its image
    assert [q for q, _ in into_prior] == list(range(17))  # each keyframe finds its own image
    assert all(place[m] == place[q] for q, m in into_prior)  # (a revisit's: a tie of two)
    assert len({(r["query_id"], r["match_session"]) for r in loops}) == 24  # one per map


def test_prior_map_bad_input(bag, first, tmp_path, tiny_model):
    def replay(**options):
        options = ReplayOptions(progress=False, robot_id="r1", session_id="tue", **options)
        return replay_bag(bag, tmp_path / "out", options, model=tiny_model, config=CONFIG)

    with pytest.raises(ConfigError, match="--prior-map .*nowhere does not exist or is not a"):
        replay(prior_maps=(tmp_path / "nowhere",))
    with pytest.raises(ConfigError, match=r"--prior-map .*map is given twice: give each folder"):
        replay(prior_maps=(first / "map", first / "map"))
    reused = ReplayOptions(
        progress=False, robot_id="r1", session_id="mon", prior_maps=(first / "map",)
    )
    with pytest.raises(
        ConfigError,
        match=r"holds 17 keyframes of robot 'r1' session 'mon', the live robot and session: a "
        r"session id names one recording, so give this run a new session_id",
    ):
        replay_bag(bag, tmp_path / "out", reused, model=tiny_model, config=CONFIG)
    with pytest.raises(MapError, match="is a prior map \\(loaded read-only\\): the live map is"):
        replay(prior_maps=(first / "map",), map_dir=first / "map", overwrite=True)
    (tmp_path / "empty").mkdir()
    with pytest.raises(MapError, match="--prior-map .*empty cannot be used: .*manifest.json is"):
        replay(prior_maps=(tmp_path / "empty",))
    assert not (tmp_path / "out" / "summary.json").exists()


def test_cli_flags_and_a_prior_map_of_another_model(bag, first, tmp_path, tiny_model, capsys):
    weights = save_pairvpr(tiny_model, tmp_path / "tiny.pth")  # another fingerprint (a file)
    out = tmp_path / "cli"
    argv = [str(bag), "--weights", str(weights), "--out", str(out), "--quiet", "--top-k", "1"]
    assert main([*argv, "--robot-id", "r2", "--session-id", "wed"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["robot"], summary["session"]) == ("r2", "wed")
    capsys.readouterr()
    before = saved_map_digest(first / "map")
    argv += ["--out", str(tmp_path / "cli2"), "--prior-map", str(first / "map")]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith(
        f"error: --prior-map {first / 'map'} cannot be used: place map "
        f"{(first / 'map').resolve()} was built with model fingerprint 'random-init:0|"
    )
    assert "load it with the same weights and image size it was built with" in err
    assert saved_map_digest(first / "map") == before
    # with the same weights: live and prior-map loops are reported apart, each on its own line
    argv = [*argv[:8], "--out", str(tmp_path / "cli3"), "--prior-map", str(out / "map")]
    assert main([*argv, "--robot-id", "r2", "--session-id", "thu", "--threshold=-1e9"]) == 0
    lines = capsys.readouterr().out.splitlines()
    summary = json.loads((tmp_path / "cli3" / "summary.json").read_text())
    prior, live = summary["prior_evaluation"], summary["loops_by_match"].get("r2/thu", 0)
    assert prior["accepted"] == summary["loops"] - live > 0 and prior["unlabelled_accepted"] == 0
    assert prior["covered"] == prior["prior_keyframes"] > 0  # the map of this bag: all covered
    assert lines[-6].startswith("live loops: precision "), lines  # then prior-map loops, the
    assert lines[-3].startswith("report: ")  # suggestion, report, outputs, the summary line
    assert lines[-5].startswith(
        f"prior-map loops: {prior['accepted']} ({prior['true_accepted']} true, "
        f"{prior['false_accepted']} false, 0 unlabelled: {prior['covered']} of "
        f"{prior['covered']} prior keyframes have ground truth), precision "
    )
    assert (
        f"loops {summary['loops']} ({live} live, {prior['accepted']} into prior maps)"
        in (lines[-1])
    )
