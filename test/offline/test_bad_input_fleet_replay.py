"""Bad-input matrix, `pairvpr-fleet-replay`: robots repeated or alone, missing sources, bad
fleet parameters, an output folder that holds a run (left unchanged) or is a file."""

from __future__ import annotations

import re

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
        2,
        "error: --robot c s1 {tmp}/none: no bag or image folder at {tmp}/none",
    ),  # fmt: skip
    "negative budget": (
        lambda root, tmp: argv(root, "--params-file", params(tmp / "p.yaml", "fleet_budget: -1")),
        1,
        "fleet_budget=-1 is out of range [0, 1000]",
    ),  # fmt: skip
    "peers naming only the robot": (
        lambda root, tmp: argv(root, "--params-file", params(tmp / "p.yaml", 'fleet_peers: "a"')),
        1,
        "error: fleet_peers ['a'] name only robot 'a' itself: list the robots it listens to, "
        "or '' for every robot",
    ),  # fmt: skip
    "peers naming no robot of the run": (
        lambda root, tmp: argv(root, "--params-file", params(tmp / "p.yaml", 'fleet_peers: "z"')),
        1,
        "error: fleet_peers names robot 'z', which is no --robot of this run (['a', 'b']): list "
        "robots of the run, or '' for every robot",
    ),  # fmt: skip
    "peers naming a bad id": (
        lambda root, tmp: argv(
            root, "--params-file", params(tmp / "p.yaml", 'fleet_peers: "a.b"')
        ),
        1,
        "error: parameter file {tmp}/p.yaml: fleet_peers robot 'a.b' must be 1-64 characters of "
        "ASCII letters, digits or '_'",
    ),  # fmt: skip
    "robot id too long": (
        lambda root, tmp: argv(root).__add__(["--robot", "r" * 65, "s", str(root / "a")]),
        2,
        f"error: --robot {'r' * 65} s {{root}}/a: robot id 'rrrr",
    ),  # fmt: skip
    "session id '..'": (
        lambda root, tmp: argv(root).__add__(["--robot", "c", "..", str(root / "a")]),
        2,
        "error: --robot c .. {root}/a: session id '..' must be 1-64 characters of ASCII letters, "
        "digits or '_' (a robot id starts with a letter): it names folders, a ROS topic and "
        "pose-graph keys, e.g. 20261125T093000Z",
    ),  # fmt: skip
    "--out is under a file": (
        lambda root, tmp: argv(root)[:-2] + ["--out", str(_file(tmp) / "sub")],
        1,
        "error: --out {tmp}/file/sub is not a folder ({tmp}/file is a file): give a folder",
    ),  # fmt: skip
    "--out cannot be written": (
        lambda root, tmp: argv(root)[:-2] + ["--out", "/proc/fleet_out"],
        1,
        "error: cannot write --out /proc/fleet_out: /proc is not writable (",
    ),  # fmt: skip
}

RULE = (
    "must be 1-64 characters of ASCII letters, digits or '_' (a robot id starts with a letter): "
    "it names folders, a ROS topic and pose-graph keys, e.g. robot1"
)
for _bad in ["..", ".", "x.y", "a@b", "fleet_summary.json", "inter_robot_loops.json", "a/b"]:
    CASES[f"robot id {_bad!r}"] = (
        lambda root, tmp, bad=_bad: argv(root) + ["--robot", bad, "s1", str(root / "a")],
        2,
        f"error: --robot {_bad} s1 {{root}}/a: robot id {_bad!r} {RULE}",
    )


@pytest.mark.parametrize("case", CASES)
def test_bad_fleet_replay_input_is_an_error_line(folders, tmp_path, capsys, case):
    make, code, message = CASES[case]
    (folders / "loops.json").write_text("[]\n")  # what a robot '..' would have replaced
    before = tree_digest(folders)
    assert main(make(folders, tmp_path)) == code
    assert message.format(root=folders, tmp=tmp_path) in capsys.readouterr().err
    assert not (folders / "out").exists() and tree_digest(folders) == before


def _file(tmp):
    (tmp / "file").write_text("x")
    return tmp / "file"


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


def test_fleet_peers_reach_every_robot_but_itself(folders, tmp_path, monkeypatch):
    """fleet_peers is honoured (issue 38): each robot listens to the listed others."""
    import pair_vpr_ros.offline.fleet.cli as cli
    from pair_vpr_ros.offline.fleet.replay import FleetRun, robot_fleet

    seen = {}
    monkeypatch.setattr(cli, "run_fleet", lambda robots, model, d, fleet, g, progress: (
        seen.update(fleet=fleet), FleetRun())[1])  # fmt: skip
    args = argv(folders, "--params-file", params(tmp_path / "p.yaml", 'fleet_peers: "a, b"'))
    args[args.index("--out") + 1] = str(tmp_path / "out")
    assert main(args) == 0
    assert seen["fleet"]["peers"] == ("a", "b")
    assert robot_fleet(seen["fleet"], "a")["peers"] == ("b",)
    assert robot_fleet(seen["fleet"], "c")["peers"] == ("a", "b")


@pytest.mark.parametrize("robot", ["..", ".", "fleet_summary.json"])
def test_no_robot_id_can_write_outside_out(tmp_path, robot):
    """The library refuses what the command line refuses: no folder outside --out."""
    from pair_vpr_ros.errors import ConfigError
    from pair_vpr_ros.offline.fleet.replay import FleetRun, write_fleet_run

    (tmp_path / "loops.json").write_text("[]\n")
    before = tree_digest(tmp_path)
    with pytest.raises(ConfigError, match=f"^robot_id {re.escape(repr(robot))} must be 1-64"):
        write_fleet_run(FleetRun(robot_loops={robot: [{"x": 1}]}), tmp_path / "out")
    assert tree_digest(tmp_path) == before and not (tmp_path / "out").exists()


def test_a_full_disk_while_writing_the_results_is_an_output_error(tmp_path, monkeypatch):
    import errno

    from pair_vpr_ros.errors import OutputError
    from pair_vpr_ros.offline.fleet import replay

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(replay, "_write_json", full)
    with pytest.raises(OutputError) as err:
        replay.write_fleet_run(replay.FleetRun(robot_loops={"a": []}), tmp_path / "out")
    assert str(err.value) == (
        f"cannot write the fleet run's outputs into {tmp_path / 'out'}: the disk is full (No "
        f"space left on device), writing {tmp_path / 'out' / 'inter_robot_loops.json'}; free "
        "space or pick another --out"
    )


def test_a_full_disk_under_the_writes_names_the_file_and_leaves_no_tmp(tmp_path, monkeypatch):
    """Issue 48: the OS fails the write itself (no file name in its error): the file is named
    all the same, and its .tmp is not left behind (before: "(None)", inter_robot_loops.tmp)."""
    import errno
    from pathlib import Path

    from pair_vpr_ros.errors import OutputError
    from pair_vpr_ros.offline.fleet import replay

    def full(self, data, *args, **kwargs):
        Path.write_bytes(self, data[:10].encode())  # what a full disk leaves: a partial file
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full)
    with pytest.raises(OutputError) as err:
        replay.write_fleet_run(replay.FleetRun(robot_loops={"a": []}), tmp_path / "out")
    assert str(err.value) == (
        f"cannot write the fleet run's outputs into {tmp_path / 'out'}: the disk is full (No "
        f"space left on device), writing {tmp_path / 'out' / 'inter_robot_loops.json'}; free "
        "space or pick another --out"
    )
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == []
