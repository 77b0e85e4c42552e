"""`pairvpr-posegraph --trajectory ...`: several robot-sessions' bags and replays -> one
optimised TUM per robot-session, all in the first one's frame."""

from __future__ import annotations

import json
from dataclasses import asdict

import fleet_drives as fd
import numpy as np
import pytest
from test_posegraph_cli import CAMERA, loop_record, write_odometry_bag

from pair_vpr_ros.messages.factor import IDENTITY
from pair_vpr_ros.messages.loop import record_dict
from pair_vpr_ros.offline.posegraph.cli import main
from pair_vpr_ros.offline.report.trajectories import read_tum

SHIFT = 60


def write_loops(path, factors, identity: bool) -> None:
    """loops.json of ``factors``; without ``identity`` as a replay without --robot-id writes."""
    records = []
    for f in factors:
        record = record_dict(loop_record(f))
        if identity:
            record.update({k: getattr(f, k) for k in IDENTITY})
        records.append(record)
    path.mkdir(parents=True, exist_ok=True)
    (path / "loops.json").write_text(json.dumps(records))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    """Bags of robots a and b (odometry in their own frames, truth in the world), a's replay
    without identities (its own loops), b's with them (its own loops and loops into a)."""
    root = tmp_path_factory.mktemp("fleet")
    a, b = fd.robot(0, seed=1), fd.robot(SHIFT, seed=2)
    rng = np.random.default_rng(0)
    A, B = ("a", "s1"), ("b", "s1")
    within_a = fd.loops(a, a, A, A, 0, rng, start=a[3])
    b_loops = fd.loops(b, b, B, B, 0, rng, start=b[3])
    b_loops += fd.loops(b, a, B, A, SHIFT, rng, start=100)
    for name, drive in (("a", a), ("b", b)):
        write_odometry_bag(root / f"{name}_bag", drive[0], {"/odom": drive[2], "/truth": drive[1]})
    write_loops(root / "replay_a", within_a, identity=False)
    write_loops(root / "replay_b", b_loops, identity=True)
    return root, len(within_a), len(b_loops)


def argv(root, *extra) -> list[str]:
    return ["--trajectory", "a", "s1", str(root / "a_bag"), "--trajectory", "b", "s1",
            str(root / "b_bag"), "--loops-of", "a", "s1", str(root / "replay_a"),
            "--loops", str(root / "replay_b"), "--camera-to-base", CAMERA, *extra]  # fmt: skip


def test_two_robots_end_in_one_frame(fleet, tmp_path, capsys):
    root, n_a, n_b = fleet
    out = tmp_path / "out"
    assert main(argv(root, "--gt-topic", "/truth", "--out", str(out))) == 0
    printed = capsys.readouterr().out
    summary = json.loads((out / "posegraph.json").read_text())
    assert summary["loops_added"] == n_a + n_b and summary["skipped"] == {}
    for name in ("a/s1", "b/s1"):
        item = summary["trajectories"][name]
        errors = item["errors"]
        before, after = errors["odometry"]["ate_rmse"], errors["optimised"]["ate_rmse"]
        assert item["joined"] and after < before / 5 and after < 0.5, (name, before, after)
        assert errors["ate_in_reference_frame"] < 1.0
        assert f"{name}: {item['nodes']} nodes, " in printed
        assert len(read_tum(out / name / "optimised.tum")) == item["nodes"]
        assert (out / name / "ground_truth.tum").is_file()
    assert summary["trajectories"]["b/s1"]["loops_between"] > 0
    assert summary["trajectories"]["a/s1"]["loops_within"] == n_a
    assert (out / "posegraph.png").read_bytes()[:4] == b"\x89PNG"
    assert "outputs in" in printed and "joined" in printed


def test_the_single_robot_form_keeps_its_files(fleet, tmp_path):
    root, _, _ = fleet
    out = tmp_path / "one"
    assert main([str(root / "a_bag"), "--loops", str(root / "replay_a"), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "odometry.tum", "optimised.tum", "posegraph.json", "posegraph.png"
    ]  # fmt: skip
    assert asdict  # the summary is the single robot's: no trajectories section
    assert "trajectories" not in json.loads((out / "posegraph.json").read_text())
