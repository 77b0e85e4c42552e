"""Bad-input matrix, the demo fleet's exchange loops (`python -m pair_vpr_ros.offline.fleet.loops`)
FLEET: each case a clear error with exact words; nothing written, no input changed."""

from __future__ import annotations

import json

import pytest
from bad_input import tree_digest

from pair_vpr_ros.offline.fleet.loops import main

LOOP = {"query_robot": "b", "query_session": "s1", "query_stamp": 1.0, "match_robot": "a",
        "match_session": "s1", "match_stamp": 1.0, "accepted": True}  # fmt: skip


@pytest.fixture
def fleet(tmp_path):
    drives = [{"robot": r, "session": "s1", "bag": f"{r}_s1"} for r in ("a", "b")]
    (tmp_path / "fleet.json").write_text(json.dumps({"drives": drives}))
    for d in drives:
        (tmp_path / "replay" / f"{d['robot']}_s1").mkdir(parents=True)
        (tmp_path / "replay" / f"{d['robot']}_s1" / "loops.json").write_text("[]")
    (tmp_path / "exchange").mkdir()
    (tmp_path / "exchange" / "inter_robot_loops.json").write_text(json.dumps([LOOP]))
    return tmp_path


CASES = [
    ("no exchange run", "exchange/inter_robot_loops.json", None,
     "error: no fleet exchange in {root}: {root}/exchange/inter_robot_loops.json missing (run "
     "pairvpr-fleet-replay --out {root}/exchange first)"),
    ("exchange loops not JSON", "exchange/inter_robot_loops.json", "[{",
     "error: cannot read loops {root}/exchange/inter_robot_loops.json: Expecting property name"),
    ("exchange loops not a list", "exchange/inter_robot_loops.json", '{"a": 1}',
     "error: loops {root}/exchange/inter_robot_loops.json is not a JSON list of loop records"),
    ("a replay missing", "replay/b_s1/loops.json", None,
     "error: no replay of b/s1: {root}/replay/b_s1/loops.json missing"),
    ("a replay not a list", "replay/a_s1/loops.json", "7",
     "error: loops {root}/replay/a_s1/loops.json is not a JSON list of loop records"),
]  # fmt: skip


@pytest.mark.parametrize(("case", "path", "text", "message"), CASES, ids=[c[0] for c in CASES])
def test_bad_exchange_loops(fleet, capsys, case, path, text, message):
    if text is None:
        (fleet / path).unlink()
    else:
        (fleet / path).write_text(text)
    before = tree_digest(fleet)
    assert main([str(fleet)]) == 1
    assert message.format(root=fleet) in capsys.readouterr().err
    assert tree_digest(fleet) == before  # nothing written (no added_loops.json)


def test_good_input_adds_the_loop(fleet):
    assert main([str(fleet)]) == 0
    added = json.loads((fleet / "exchange" / "added_loops.json").read_text())
    assert added == [LOOP]
