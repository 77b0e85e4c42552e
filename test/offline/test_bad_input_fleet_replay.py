"""Bad-input matrix, `pairvpr-fleet-replay`: robots repeated or alone, missing sources, bad
fleet parameters, an output folder that holds a run (left unchanged) or is a file."""

from __future__ import annotations

import numpy as np
import pytest
from bad_input import tree_digest
from synthetic_data import write_rgb

from pair_vpr_ros.offline.fleet.cli import main


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    rng = np.random.default_rng(0)
    for robot in "ab":
        write_rgb(root / robot / "000.png", rng.integers(0, 256, (32, 32, 3), dtype=np.uint8))
    return root


def argv(root, *extra, robots="ab"):
    out = []
    for r in robots:
        out += ["--robot", r, "s1", str(root / r)]
    return [*out, "--weights", "random-tiny", "--quiet", "--out", str(root / "out"), *extra]


def params(path, text):
    path.write_text("/**:\n  ros__parameters:\n    " + text + "\n")
    return str(path)


CASES = {
    "one robot": (
        lambda root, tmp: argv(root, robots="a"),
        2,
        "error: --robot: give at least two robots",
    ),  # fmt: skip
    "same id twice": (
        lambda root, tmp: argv(root, robots="aa"),
        1,
        "error: fleet robots ['a', 'a'] repeat an id: give each robot its own",
    ),  # fmt: skip
    "missing source": (
        lambda root, tmp: argv(root) + ["--robot", "c", "s1", str(tmp / "none")],
        1,
        "does not exist",
    ),  # fmt: skip
    "negative budget": (
        lambda root, tmp: argv(root, "--params-file", params(tmp / "p.yaml", "fleet_budget: -1")),
        1,
        "fleet_budget=-1 is out of range [0, 1000]",
    ),  # fmt: skip
    "peers naming the robot": (
        lambda root, tmp: argv(root, "--params-file", params(tmp / "p.yaml", 'fleet_peers: "a"')),
        1,
        "error: fleet peers ['a'] name this robot 'a'",
    ),  # fmt: skip
    "robot id too long": (
        lambda root, tmp: argv(root).__add__(["--robot", "r" * 65, "s", str(root / "a")]),
        1,
        "error: fleet robot 'rrrr",
    ),  # fmt: skip
}


@pytest.mark.parametrize("case", CASES)
def test_bad_fleet_replay_input_is_an_error_line(folders, tmp_path, capsys, case):
    make, code, message = CASES[case]
    assert main(make(folders, tmp_path)) == code
    assert message in capsys.readouterr().err
    assert not (folders / "out").exists()


def test_an_output_folder_holding_a_run_is_not_replaced(folders, tmp_path, capsys):
    out = tmp_path / "out"
    args = argv(folders)
    args[args.index("--out") + 1] = str(out)
    assert main(args) == 0
    before = tree_digest(out)
    assert main(args) == 1
    assert f"error: --out {out} holds a fleet run already (fleet_summary.json)" in (
        capsys.readouterr().err
    )
    assert tree_digest(out) == before
    assert main([*args, "--overwrite"]) == 0


def test_an_output_path_that_is_a_file(folders, tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    args = argv(folders)
    args[args.index("--out") + 1] = str(tmp_path / "file")
    assert main(args) == 1
    assert "is a file: give a folder" in capsys.readouterr().err
