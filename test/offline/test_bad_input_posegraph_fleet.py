"""Bad-input matrix, pose graph of several robot-sessions (issue 22 part 5): pairvpr-posegraph
--trajectory and posegraph_node's `trajectories` and `prior_map_dirs`. Each case is a clear
error with exact words or a counted skip; nothing is written for an error."""

from __future__ import annotations

import json

import fleet_drives as fd
import numpy as np
import pytest
from bad_input import tree_digest
from map_fixtures import make_map, save_keyframes
from test_posegraph_cli import write_odometry_bag
from test_posegraph_fleet_cli import write_loops

from pair_vpr_ros.errors import ConfigError, MapError
from pair_vpr_ros.offline.posegraph.cli import main
from pair_vpr_ros.params.posegraph import parse_trajectories
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.priors import graph_with_priors, read_prior_sessions

IDENTITY7 = (0, 0, 0, 0, 0, 0, 1)


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
    write_loops(root / "unnamed", stranger, identity=False)  # a replay without --robot-id
    write_loops(root / "none", [], identity=True)
    return root, len(stranger)


def trajectory(root, robot, session, bag) -> list[str]:
    return ["--trajectory", robot, session, str(root / bag)]


CASES = [
    ("same robot-session twice", ["a", "s1", "a"], ["a", "s1", "b"], 1,
     "error: --trajectory 1 and 2 are both robot a session s1: two robots need two robot ids, two "
     "runs of one robot two session ids"),
    ("robot id with a slash", ["a", "s1", "a"], ["b/x", "s1", "b"], 1,
     "error: --trajectory 2: robot id 'b/x' must be 1-64 characters of ASCII letters, digits or "
     "'_' (a robot id starts with a letter): it names folders, a ROS topic and pose-graph keys, "
     "e.g. robot1"),
    ("session id '..'", ["a", "..", "a"], ["b", "s1", "b"], 1,
     "error: --trajectory 1: session id '..' must be 1-64 characters of ASCII letters"),
    ("robot id '.'", ["a", "s1", "a"], [".", "s1", "b"], 1,
     "error: --trajectory 2: robot id '.' must be 1-64 characters"),
    ("robot id 'posegraph.json'", ["a", "s1", "a"], ["posegraph.json", "s1", "b"], 1,
     "error: --trajectory 2: robot id 'posegraph.json' must be 1-64 characters"),
    ("robot id 'x.y'", ["a", "s1", "a"], ["x.y", "s1", "b"], 1,
     "error: --trajectory 2: robot id 'x.y' must be 1-64 characters"),
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


@pytest.mark.parametrize(
    ("out", "message"),
    [
        ("{tmp}/file", "error: --out {tmp}/file is not a folder: give a folder"),
        ("{tmp}/file/sub", "error: --out {tmp}/file/sub is not a folder ({tmp}/file is a file)"),
        ("/proc/pg_out", "error: cannot write --out /proc/pg_out: /proc is not writable ("),
    ],
)  # fmt: skip
def test_a_bad_out_is_refused_before_the_work(bags, tmp_path, capsys, out, message):
    """Issue 38: --out checked first (a file, under a file, not writable): nothing is lost."""
    root, _ = bags
    (tmp_path / "file").write_text("x")
    for argv in ([*trajectory(root, "a", "s1", "a"), *trajectory(root, "b", "s1", "b"),
                  "--loops", str(root / "none")],
                 [str(root / "a"), "--loops", str(root / "none")]):  # fmt: skip
        assert main([*argv, "--out", out.format(tmp=tmp_path)]) == 1
        cap = capsys.readouterr()
        assert message.format(tmp=tmp_path) in cap.err and "Traceback" not in cap.err
        assert "loops in the graph" not in cap.out  # refused before the graph was built
    assert (tmp_path / "file").read_text() == "x"


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
        (["--trajectory", "a", "s1", "{root}/a", "--loops-of", "..", "s1", "{root}/none"], 2,
         "error: --loops-of: robot id '..' must be 1-64 characters of ASCII letters, digits or "
         "'_' (a robot id starts with a letter)"),
        (["--trajectory", "a", "s1", "{root}/a", "--loops-of", "a", "s@1", "{root}/none"], 2,
         "error: --loops-of: session id 's@1' must be 1-64 characters"),
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
        (
            "../s1=/odom",
            "trajectories: robot id '..' must be 1-64 characters of ASCII letters, "
            "digits or '_' (a robot id starts with a letter): it names folders, a ROS topic and "
            "pose-graph keys, e.g. robot1",
        ),
        ("a/x.y=/odom", "trajectories: session id 'x.y' must be 1-64 characters"),
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


# ---- posegraph_node's prior_map_dirs (posegraph.priors): refused before the graph is built, no
# prior map changes; unusable keyframes are counted skips.
def _damaged(t):
    d = make_map(t / "d", "a", "day1", 2, seed=1)
    (d / "map-1.sqlite").write_bytes(b"x")
    return [d]


PRIOR_CASES = {
    "missing": (lambda t: [t / "none"], ConfigError,
                "prior_map_dirs: {t}/none does not exist or is not a folder: give the folder of a "
                "saved place map (vpr_node's save_map, a replay's map/)"),
    "a file": (lambda t: [t / "file"], ConfigError,
               "prior_map_dirs: {t}/file does not exist or is not a folder"),
    "not a map": (lambda t: [t / "empty"], MapError,
                  "prior_map_dirs: {t}/empty cannot be used: {t}/empty/manifest.json is missing: "
                  "{t}/empty is not a saved place map"),
    "damaged": (_damaged, MapError,
                "prior_map_dirs: {t}/d cannot be used: keyframe store {t}/d/map-1.sqlite cannot "
                "be read (no such table: keyframes)"),
    "given twice": (lambda t: [make_map(t / "a", "a", "day1", 2, seed=1), t / "a" / ".." / "a"],
                    ConfigError, "prior_map_dirs: {t}/a/../a is given twice: give each folder "
                    "once"),
    "a prior session live too": (lambda t: [make_map(t / "a", "b", "s1", 2, seed=1)], ConfigError,
                                 "trajectories: robot-session b/s1 is a prior session (in {t}/a): "
                                 "a session id names one recording, so give the live robot a new "
                                 "session id (or leave SESSION empty)"),
    "more sessions than keys": (
        lambda t: [save_keyframes(t / "m", [(1.0, IDENTITY7, f"r{i}", "s") for i in range(52)])],
        ConfigError, "a pose graph holds at most 52 robot-sessions (prior sessions: 52)"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(PRIOR_CASES))
def test_bad_prior_maps_are_refused_and_unchanged(tmp_path, case):
    build, error, message = PRIOR_CASES[case]
    (tmp_path / "file").write_text("x")
    (tmp_path / "empty").mkdir()
    dirs = build(tmp_path)
    before = tree_digest(tmp_path)
    with pytest.raises(error) as err:
        graph_with_priors(PoseGraphConfig(), read_prior_sessions(dirs), [("b", "s1")])
    assert message.format(t=tmp_path) in str(err.value)
    assert tree_digest(tmp_path) == before


def test_prior_keyframes_that_cannot_be_used_are_counted(tmp_path):
    """No pose, no robot or session, a zero quaternion, a stamp given twice: counted skips; a
    session left without a keyframe is no trajectory, and a loop into it a counted skip."""
    path = save_keyframes(tmp_path / "m", [
        (1.0, IDENTITY7, "a", "day1"), (2.0, None, "a", "day1"), (3.0, IDENTITY7, "", "day1"),
        (4.0, (0, 0, 0, 0, 0, 0, 0), "a", "day1"), (1.0, IDENTITY7, "a", "day1"),
        (5.0, None, "c", "day1"),
    ])  # fmt: skip
    graph = graph_with_priors(PoseGraphConfig(), read_prior_sessions([path]), [("b", "s1")])
    assert [t.trajectory for t in graph.tracks] == [("a", "day1"), ("b", "s1")]
    assert graph.counts.odometry == 1
    assert graph.counts.skipped == {
        "prior keyframe: no pose": 2,
        "prior keyframe: no robot or session (a loop cannot name it)": 1,
        "prior keyframe: pose has a zero quaternion": 1,
        "prior keyframe: stamp of another keyframe of its session": 1,
    }
    b = fd.robot(0, seed=2, laps=1)
    for stamp, pose in zip(b[0][:20], b[2][:20], strict=True):
        graph.add_odometry(float(stamp), tuple(pose), ("b", "s1"))
    loop = fd.loops(b, b, ("b", "s1"), ("c", "day1"), 0, np.random.default_rng(0), stop=10)[0]
    assert graph.add_loop(loop).startswith("robot-session c/day1 is not in the graph")
    assert graph.counts.skipped["loop: robot-session c/day1 is not in the graph"] == 1


def test_a_prior_map_of_any_model_is_read(tmp_path):
    """The graph needs the keyframes' poses only: no model fingerprint is checked."""
    path = make_map(tmp_path / "m", "a", "day1", 3, seed=1, fingerprint="model-b")
    priors = read_prior_sessions([path])
    assert priors.trajectories == [("a", "day1")] and priors.sessions[0].stamps.tolist() == [
        10.0, 11.0, 12.0
    ]  # fmt: skip


def test_a_full_disk_while_writing_is_one_error_line(bags, tmp_path, capsys, monkeypatch):
    """Issue 38 #6: the graph's outputs cannot be written (disk full): an error naming the
    file, not a bare OSError traceback."""
    import errno

    from pair_vpr_ros.offline.posegraph import fleet

    def full(path, trajectory):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(fleet, "write_tum", full)
    root, _ = bags
    out = tmp_path / "out"
    argv = [*trajectory(root, "a", "s1", "a"), *trajectory(root, "b", "s1", "b"), "--loops",
            str(root / "none"), "--out", str(out)]  # fmt: skip
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.endswith(
        f"error: cannot write the pose graph's outputs into {out}: the disk is full (No space "
        f"left on device), writing {out / 'a' / 's1' / 'odometry.tum'}; free space or pick "
        "another --out\n"
    )


def test_a_full_disk_under_evo_s_writer_names_the_file(bags, tmp_path, capsys, monkeypatch):
    """Issue 48: evo's own write fails (no file name in the OS error): named, never "(None)"."""
    import errno

    from evo.tools import file_interface

    def full(path, trajectory):
        open(path, "w").write("partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(file_interface, "write_tum_trajectory_file", full)
    root, _ = bags
    out = tmp_path / "out"
    argv = [*trajectory(root, "a", "s1", "a"), *trajectory(root, "b", "s1", "b"), "--loops",
            str(root / "none"), "--out", str(out)]  # fmt: skip
    assert main(argv) == 1
    assert capsys.readouterr().err.endswith(
        f"error: cannot write the pose graph's outputs into {out}: the disk is full (No space "
        f"left on device), writing {out / 'a' / 's1' / 'odometry.tum'}; free space or pick "
        "another --out\n"
    )
    assert not (out / "a" / "s1" / "odometry.tum").exists()


def test_loops_that_name_no_robot_get_advice_that_can_be_followed(bags, tmp_path, capsys):
    """Issue 48: loops of a replay without --robot-id ('*/*') among several trajectories: the
    advice is --loops-of, not a --trajectory for '*/*'."""
    root, count = bags
    argv = [*trajectory(root, "a", "s1", "a"), *trajectory(root, "b", "s1", "b"), "--loops",
            str(root / "unnamed"), "--out", str(tmp_path / "out")]  # fmt: skip
    assert main(argv) == 0
    assert (
        f"warning: {count} loops skipped: robot-session */* is not in the graph (the loops name "
        "no robot or session (a replay without "
        "--robot-id): give each such loops file as --loops-of ROBOT SESSION PATH, the "
        "robot-session it was replayed for)"
    ) in capsys.readouterr().err
