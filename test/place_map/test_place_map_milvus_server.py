"""Index kind "milvus" on a Milvus server only: two processes writing one collection of the
test server (milvus_fixtures.py) at once and both restarting; on a second server of its own
(other ports, authorization on), a wrong token and a kill -9 of the server during a run; and
scripts/milvus_server.sh when the server never comes up."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_place_map_persist import DIM, SHAPE, add_range, desc_for

from pair_vpr_ros.errors import MapError, MapUnavailableError
from pair_vpr_ros.place_map import IndexConfig, PlaceMap

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "milvus_server.sh"

# One robot's process: its own keyframes and those it hears from the other robot, each search
# under its own exclusion rules (own robot: not the newest 3, not within 5 s), then saved.
WRITER = """
import sys, numpy as np
from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.milvus.expr import Exclusion
uri, name, robot, other, out, start, stop = sys.argv[1:8]
config = IndexConfig(kind="milvus", milvus_uri=uri, milvus_collection=name, milvus_index="FLAT")
loaded = start != "0"
m = PlaceMap.load(out, "fp") if loaded else PlaceMap(8, (4, 8), "fp", index=config)
rng = np.random.default_rng(int(start) + len(robot))
for i in range(int(start), int(stop)):
    who = robot if i % 3 else other  # every third keyframe heard from the other robot
    d = rng.normal(size=8).astype(np.float32)
    m.add(d / np.linalg.norm(d), np.zeros((4, 8), np.float32),
          KeyframeMeta(stamp=float(i), robot=who, session="s"))
    rule = Exclusion(float(i), 5.0, max(0, len(m) - 3), robot, "s")
    for kf, _ in m.search(d, 5, exclusion=rule):
        meta = m.meta(kf)
        assert meta.robot != robot or (abs(meta.stamp - i) >= 5 and kf < len(m) - 3), kf
m.save(out)
print(m._index.writer)
"""


def _writers(config: IndexConfig, tmp_path: Path, start: int, stop: int) -> list[int]:
    """Two robots' processes writing `config`'s collection at once -> their writer keys."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                WRITER,
                config.milvus_uri,
                config.milvus_collection,
                robot,
                other,
                str(tmp_path / robot),
                str(start),
                str(stop),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )  # fmt: skip
        for robot, other in (("a", "b"), ("b", "a"))
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err[-2000:] for _, err in outs]
    return [int(out.split()[-1]) for out, _ in outs]


def _keys(config: IndexConfig) -> list[int]:
    from pymilvus import MilvusClient

    client = MilvusClient(config.milvus_uri, token=os.environ.get(config.milvus_token_env, ""))
    rows = client.query(config.milvus_collection, filter="pk >= 0", output_fields=["pk"],
                        limit=16384, consistency_level="Strong")  # fmt: skip
    client.close()
    return [int(r["pk"]) for r in rows]


@pytest.mark.slow  # two processes, twice (~30 s)
def test_two_processes_write_one_collection_and_restart(server_milvus, tmp_path):
    """Every acknowledged (saved) keyframe of both robots is in the collection exactly once,
    after writing at once and after both restart from their folders and continue."""
    writers = _writers(server_milvus, tmp_path, 0, 40)
    assert writers[0] != writers[1]
    keys = _keys(server_milvus)
    want = {w << 32 | i for w in writers for i in range(40)}
    assert len(keys) == len(set(keys)) == 80 and set(keys) == want
    assert _writers(server_milvus, tmp_path, 40, 60) == writers  # restarted: same keys
    keys = _keys(server_milvus)
    assert len(keys) == len(set(keys)) == 120
    assert set(keys) == {w << 32 | i for w in writers for i in range(60)}
    for robot in ("a", "b"):
        with PlaceMap.load(tmp_path / robot, "fp", read_only=True) as m:
            assert len(m) == 60
            robots = {m.meta(i).robot for i in range(60)}
            assert robots == {"a", "b"}  # its own keyframes and the other robot's


def _wait(predicate, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < end, f"{what} after {timeout_s} s"
        time.sleep(0.5)


def _answers(m: PlaceMap, i: int) -> bool:
    try:
        return m.search(desc_for(i), 1)[0][0] == i
    except MapUnavailableError:
        return False


FAULT_SHIFT = 100  # the fault server's ports: client 19630, health 9191
FAULT_URI = f"http://127.0.0.1:{19530 + FAULT_SHIFT}"
TOKEN = "root:Milvus"  # the default user of a Milvus server with authorization


def _fault_script(action: str, timeout_s: int = 600) -> subprocess.CompletedProcess:
    """scripts/milvus_server.sh on the fault server's own ports and data folder."""
    env = {
        **os.environ,
        "MILVUS_PORT_SHIFT": str(FAULT_SHIFT),
        "MILVUS_AUTH": "1",
        "MILVUS_DATA": str(ROOT / ".milvus-data-faults"),
        "MILVUS_START_TIMEOUT": "300",
    }
    return subprocess.run(["bash", str(SCRIPT), action], env=env, capture_output=True,
                          text=True, timeout=timeout_s)  # fmt: skip


@pytest.fixture
def fault_server():
    """A second Milvus server of this test's own (authorization on, other ports, its own
    data folder, emptied first): killing it leaves the shared test server alone."""
    venv = Path(os.environ.get("MILVUS_VENV", ROOT / ".venv-milvus"))
    if not (venv / "bin" / "milvus-server").is_file():
        why = f"no Milvus server venv at {venv} (scripts/milvus_server.sh start makes it)"
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true needs the fault server: {why}")
        pytest.skip(why)
    shutil.rmtree(ROOT / ".milvus-data-faults" / "data", ignore_errors=True)
    proc = _fault_script("start")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    yield IndexConfig(
        kind="milvus",
        milvus_uri=FAULT_URI,
        milvus_collection="faults",
        milvus_index="FLAT",
        milvus_token_env="PAIRVPR_TEST_FAULT_TOKEN",
    )
    _fault_script("stop")


@pytest.mark.slow  # its own server: start, kill -9, restart (~40-60 s on the 2-core VM)
def test_a_server_killed_and_restarted_during_a_run(fault_server, monkeypatch, tmp_path):
    """A wrong or missing token is a clear error. kill -9 of the server mid-run: keyframes
    are kept, searches skipped and counted; after the restart the kept keyframes go in, and a
    load of the saved map holds every keyframe once (the server may lose rows it acknowledged
    just before the kill: the load re-inserts them from the map's own copy)."""
    for token, given in (("root:wrong", "the token in $PAIRVPR_TEST_FAULT_TOKEN"),
                         (None, "no token ($PAIRVPR_TEST_FAULT_TOKEN is unset)")):  # fmt: skip
        if token is None:
            monkeypatch.delenv("PAIRVPR_TEST_FAULT_TOKEN", raising=False)
        else:
            monkeypatch.setenv("PAIRVPR_TEST_FAULT_TOKEN", token)
        with pytest.raises(MapError) as err:
            PlaceMap(DIM, SHAPE, "fp", index=fault_server)
        assert str(err.value) == (
            f"Milvus server {FAULT_URI} answers but refused the connection with {given} (Fail "
            f"connecting to server on 127.0.0.1:{19530 + FAULT_SHIFT}, illegal connection "
            "params or server unavailable): a server with authorization needs a valid "
            "'user:password' or API key in $PAIRVPR_TEST_FAULT_TOKEN; check it (and that "
            "milvus_uri is a Milvus server)"
        )
    monkeypatch.setenv("PAIRVPR_TEST_FAULT_TOKEN", TOKEN)
    m = PlaceMap(DIM, SHAPE, "fp", index=fault_server)
    add_range(m, 0, 20)
    m.save(tmp_path / "map")
    proc = _fault_script("stop")  # kill -9 of its process group
    assert proc.returncode == 0, proc.stdout + proc.stderr
    try:
        add_range(m, 20, 23)  # kept: the server is gone
        with pytest.raises(MapUnavailableError):
            m.search(desc_for(21), 1)
        assert m.index_diagnostics["map_keyframes_pending"] == 3
    finally:  # at once: the ports of the killed server are bound again (milvus_launch.py)
        proc = _fault_script("start")
        assert proc.returncode == 0, proc.stdout + proc.stderr
    _wait(lambda: _answers(m, 21), 300, "the restarted server did not answer a search")
    assert m.index_diagnostics["map_keyframes_pending"] == 0
    assert m.index_diagnostics["map_searches_skipped"] >= 1
    m.save(tmp_path / "map")
    m.close()
    with PlaceMap.load(tmp_path / "map", "fp") as again:
        assert len(again) == 23 and all(_answers(again, i) for i in (0, 19, 22))
    keys = _keys(fault_server)
    assert len(keys) == len(set(keys)) == 23


def _fake_server(tmp_path: Path, body: str) -> dict:
    """Environment for milvus_server.sh with a stand-in binary and a health URL nothing
    answers, so the real server (if any) is not touched."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    for name in ("milvus-server", "python"):  # the script runs its launcher with the venv's
        binary = venv / "bin" / name
        binary.write_text(f"#!/bin/sh\necho starting\n{body}\n")
        binary.chmod(0o755)
    fake = {"MILVUS_VENV": str(venv), "MILVUS_DATA": str(tmp_path / "data")}
    fake.update(MILVUS_HEALTH="http://127.0.0.1:9/healthz", MILVUS_START_TIMEOUT="2")
    return {**os.environ, **fake}


@pytest.mark.parametrize(
    ("body", "said"),
    [
        ("echo 'panic: address already in use'; exit 1", "the server exited before it was "
         "healthy; last lines of {data}/server.log:\nstarting\npanic: address already in use\n"),
        ("exec sleep 60", "not healthy after 2 s (MILVUS_START_TIMEOUT); stopping it; last lines "
         "of {data}/server.log:\nstarting\nmilvus: stopped (process group "),
    ],
    ids=["exits", "never healthy"],
)  # fmt: skip
def test_a_server_that_never_comes_up(tmp_path, body, said):
    env = _fake_server(tmp_path, body)
    proc = subprocess.run(["bash", str(SCRIPT), "start"], env=env, capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 1
    assert said.format(data=tmp_path / "data") in proc.stdout
    assert not (tmp_path / "data" / "server.pid").exists()
