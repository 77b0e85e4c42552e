"""Bad-input matrix, pose graph of several robot-sessions (issue 22 part 5): pairvpr-posegraph
--trajectory and posegraph_node's `trajectories`. Each case is a clear error with exact words or
a counted skip; nothing is written for an error."""

from __future__ import annotations

import json

import fleet_drives as fd
import numpy as np
import pytest
from test_posegraph_cli import write_odometry_bag
from test_posegraph_fleet_cli import write_loops

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.offline.posegraph import main
from pair_vpr_ros.posegraph.params import parse_trajectories


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad")
    a, b = fd.robot(0, seed=1, laps=1), fd.robot(30, seed=2, laps=1)
    for name, drive in (("a", a), ("b", b)):
        write_odometry_bag(root / name, drive[0], {"/odom": drive[2], "/truth": drive[1]})
    write_odometry_bag(root / "empty", [], {"/odom": np.zeros((0, 7))})
    rng = np.random.default_rng(0)
    stranger = fd.loops(b, a, ("c", "s1"), ("a", "s1"), 30, rng, every=20, stop=60)
    write_loops(root / "stranger", stranger, identity=True)
    write_loops(root / "none", [], identity=True)
    return root, len(stranger)


def trajectory(root, robot, session, bag) -> list[str]:
    return ["--trajectory", robot, session, str(root / bag)]


CASES = [
    ("same robot-session twice", ["a", "s1", "a"], ["a", "s1", "b"], 1,
     "error: --trajectory 1 and 2 are both robot a session s1: two robots need two robot ids, two "
     "runs of one robot two session ids"),
    ("robot id with a slash", ["a", "s1", "a"], ["b/x", "s1", "b"], 1,
     "error: --trajectory 2: robot id 'b/x' may hold only letters, digits, '_', '-' and '.' (it "
     "names the output folder)"),
    ("session id '..'", ["a", "..", "a"], ["b", "s1", "b"], 1,
     "error: --trajectory 1: session id '..' may hold only letters"),
    ("a robot-session with no odometry", ["a", "s1", "a"], ["b", "s1", "empty"], 1,
     "error: trajectory b/s1 ({root}/empty): odometry topic /odom has no messages"),
    ("a robot-session whose bag is missing", ["a", "s1", "a"], ["b", "s1", "missing"], 1,
     "error: trajectory b/s1 ({root}/missing): bag {root}/missing does not exist: give a "
     "rosbag2 folder"),
]  # fmt: skip


@pytest.mark.parametrize(("case", "first", "second", "code", "message"), CASES,
                         ids=[c[0] for c in CASES])  # fmt: skip
def test_bad_trajectories(bags, tmp_path, capsys, case, first, second, code, message):
    root, _ = bags
    out = tmp_path / "out"
    argv = [*trajectory(root, *first), *trajectory(root, *second), "--loops", str(root / "none"),
            "--out", str(out)]  # fmt: skip
    assert main(argv) == code
    assert message.format(root=root) in capsys.readouterr().err
    assert not out.exists()  # an error writes nothing


def test_loops_of_an_unknown_robot_are_counted_and_named(bags, tmp_path, capsys):
    root, count = bags
    out = tmp_path / "out"
    argv = [*trajectory(root, "a", "s1", "a"), *trajectory(root, "b", "s1", "b"), "--loops",
            str(root / "stranger"), "--out", str(out)]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert (f"warning: {count} loops skipped: robot-session c/s1 is not in the graph "
            "(give its --trajectory ROBOT SESSION BAG)") in err  # fmt: skip
    summary = json.loads((out / "posegraph.json").read_text())
    assert summary["skipped"] == {"loop: robot-session c/s1 is not in the graph": count}
    assert (
        "warning: b/s1 never joined the map frame (not 2 agreeing loops to the others): its "
        "optimised.tum is its odometry, in its own frame"
    ) in err
    assert (out / "b" / "s1" / "optimised.tum").is_file()


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["{root}/a", "--trajectory", "a", "s1", "{root}/a"], 2,
         "error: give one robot's BAG or several --trajectory ROBOT SESSION BAG"),
        ([], 2, "error: give one robot's BAG or several --trajectory ROBOT SESSION BAG"),
        (["--trajectory", "a", "s1"], 2, "argument --trajectory: expected 3 arguments"),
        (["--trajectory", "a", "s1", "{root}/a", "--no-loops"], 2, "unrecognized arguments"),
        (["--trajectory", "a", "s1", "{root}/a"], 2,
         "error: --trajectory needs loops: --loops PATH or --loops-of ROBOT SESSION PATH"),
        (["{root}/a", "--loops-of", "a", "s1", "{root}/none"], 2,
         "error: one robot's BAG needs --loops PATH (--loops-of goes with --trajectory)"),
        (["--trajectory", "a", "s1", "{root}/a", "--loops", "{root}/none", "--inject-false-loops",
          "0.1"], 1, "error: --inject-false-loops takes one robot's BAG, not --trajectory"),
    ],
)  # fmt: skip
def test_bad_command_lines(bags, tmp_path, capsys, args, code, message):
    root, _ = bags
    argv = [a.replace("{root}", str(root)) for a in args] + ["--out", str(tmp_path / "o")]
    assert main(argv) == code
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("a/s1", "trajectories: 'a/s1' is not ROBOT/SESSION=ODOM_TOPIC (e.g. 'a/day1=/a/odom')"),
        ("/s1=/odom", "trajectories: '/s1=/odom' is not ROBOT/SESSION=ODOM_TOPIC"),
        ("a/s/1=/odom", "trajectories: 'a/s/1=/odom' is not ROBOT/SESSION=ODOM_TOPIC"),
        ("a/s1=", "trajectories: 'a/s1=' is not ROBOT/SESSION=ODOM_TOPIC"),
        ("a/s1=/a/odom, a/s1=/b/odom", "trajectories: robot-session a/s1 is given twice"),
        ("a/s1=/odom, b/s1=/odom", "trajectories: odometry topic /odom is given twice"),
    ],
)
def test_bad_node_trajectories(text, message):
    with pytest.raises(ConfigError) as err:
        parse_trajectories(text, "odom")
    assert str(err.value) == message or message in str(err.value)


def test_node_trajectories_parse():
    assert parse_trajectories("", "odom") == [("", "", "odom")]
    assert parse_trajectories(" a/day1=/a/odom , b=/b/odom", "odom") == [
        ("a", "day1", "/a/odom"), ("b", "", "/b/odom")
    ]  # fmt: skip
