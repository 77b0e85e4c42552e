"""Bad-input matrix, prior maps (vpr_node prior_map_dirs, replay --prior-map; issue 22 part 3):
each bad folder is refused before any frame with an error naming it, nothing stays open, and no
prior map changes."""

from __future__ import annotations

import re

import pytest
from bad_input import tree_digest
from map_fixtures import make_map

from pair_vpr_ros.errors import ConfigError, MapError, MapFingerprintError
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.prior_maps import open_prior_maps

LIVE = Identity("r1", "tue")


def _missing(t):
    return [t / "none"]


def _file(t):
    (t / "file").write_text("x")
    return [t / "file"]


def _not_a_map(t):
    (t / "empty").mkdir()
    return [t / "empty"]


def _damaged(t):
    d = make_map(t / "d", "r1", "mon", 2, seed=1)
    (d / "map-1.sqlite").write_bytes(b"x")
    return [d]


CASES = {
    "missing": (
        _missing,
        ConfigError,
        "prior map {t}/none does not exist or is not a folder: give the folder of a saved place "
        "map (PlaceMap.save, vpr_node's save_map, a replay's map/)",
    ),
    "a file": (_file, ConfigError, "prior map {t}/file does not exist or is not a folder"),
    "not a map": (
        _not_a_map,
        MapError,
        "prior map {t}/empty cannot be used: {t}/empty/manifest.json is missing: {t}/empty is "
        "not a saved place map",
    ),
    "damaged": (
        _damaged,
        MapError,
        "prior map {t}/d cannot be used: keyframe store {t}/d/map-1.sqlite cannot be read (no "
        "such table: keyframes)",
    ),
    "another model": (
        lambda t: [make_map(t / "m", "r2", "mon", 2, seed=1, fingerprint="model-b")],
        MapFingerprintError,
        "prior map {t}/m cannot be used: place map {t}/m was built with model fingerprint "
        "'model-b', but the current model's fingerprint is 'model-a'",
    ),
    "given twice": (
        lambda t: [make_map(t / "a", "r2", "mon", 2, seed=1), t / "a" / ".." / "a"],
        ConfigError,
        "prior map {t}/a/../a is given twice: give each folder once",
    ),
    "session id reused": (
        lambda t: [make_map(t / "a", "r1", "tue", 3, seed=1)],
        ConfigError,
        "prior map {t}/a holds 3 keyframes of robot 'r1' session 'tue', the live robot and "
        "session: a session id names one recording, so give this run a new session_id (or leave "
        "it empty for the start time)",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_prior_map_is_refused_and_unchanged(tmp_path, case):
    build, error, message = CASES[case]
    dirs = build(tmp_path)
    before = tree_digest(tmp_path)
    with pytest.raises(error, match=re.escape(message.format(t=tmp_path))):
        open_prior_maps(dirs, "model-a", LIVE)
    assert tree_digest(tmp_path) == before


def test_the_live_map_is_never_saved_into_a_prior_map(tmp_path):
    a = make_map(tmp_path / "a", "r2", "mon", 2, seed=1)
    with pytest.raises(
        MapError,
        match=re.escape(
            f"{a} is a prior map (loaded read-only): the live map is never saved into a prior "
            "map's folder; save it to another folder"
        ),
    ):
        open_prior_maps([a], "model-a", LIVE, save_to=tmp_path / "x" / ".." / "a")
    ok = open_prior_maps([a], "model-a", LIVE, save_to=tmp_path / "live")
    assert [len(m) for m in ok.maps] == [2] and ok.summary()[0]["sessions"] == {"r2/mon": 2}
    ok.close()
