"""Crash safety of PlaceMap.save: a save killed (or failing) at any step keeps the last save.

Real crashes run in a child process that `os._exit`s from the save hook at a given step, or is
SIGKILLed while saving in a loop; failures in-process raise from the hook. Modes: "append" and
"hnsw" continue a saved map (incremental saves: one store commit; hnsw adds an index snapshot),
"fresh" and "convert" write a new generation (a new map, a format-2 map converted to 3).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from test_bad_input_map import MAPS
from test_place_map_persist import CODEC, DIM, N0, SHAPE, add_range, assert_holds

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map import IndexConfig, PlaceMap, persist

COMMITTED = persist.SAVE_STEPS.index("committed")
PRE_COMMIT = persist.SAVE_STEPS[:COMMITTED]

CHILD = """
import os, sys
sys.path.insert(0, {test_dir!r})
from test_place_map_persist import DIM, N0, SHAPE, add_range
from pair_vpr_ros.place_map import PlaceMap, persist

mode, directory, step, work = sys.argv[1:5]  # work: its temp folders, left behind by the crash
if mode in ("append", "hnsw", "convert"):  # continue the saved map and save it again in place
    m = PlaceMap.load(directory, work_dir=work)
    add_range(m, N0, N0 + 3)
elif mode == "fresh":  # a new map (dense file in the temp folder, moved) saved over the old one
    m = PlaceMap(DIM, SHAPE, "fp-a", work_dir=work)
    add_range(m, 0, 3)
elif mode == "loop":  # keep saving until killed
    m = PlaceMap.load(directory, work_dir=work)
    for i in range(N0, N0 + 10_000):
        add_range(m, i, i + 1)
        m.save(directory)
        print(i + 1, flush=True)
persist._SAVE_HOOK = lambda reached: os._exit(17) if reached == step else None
m.save(directory)
os._exit(0)
"""

pytestmark = pytest.mark.slow  # a child process killed at every save step


def run_child(tmp_path: Path, *args: str, **popen) -> subprocess.Popen:
    script = tmp_path / "child.py"
    script.write_text(CHILD.format(test_dir=str(Path(__file__).parent)))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    work = tmp_path / "work"
    work.mkdir(exist_ok=True)
    cmd = [sys.executable, str(script), *args, str(work)]
    return subprocess.Popen(cmd, env=env, **popen)


@pytest.fixture
def saved(tmp_path: Path) -> Path:
    with PlaceMap(DIM, SHAPE, "fp-a") as m:
        add_range(m, 0, N0)
        m.save(tmp_path / "map")
    return tmp_path / "map"


def _map_of(mode: str, saved: Path) -> Path:
    if mode == "convert":
        shutil.rmtree(saved)
        shutil.copytree(MAPS / "format-2", saved)
    elif mode == "hnsw":
        shutil.rmtree(saved)
        with PlaceMap(DIM, SHAPE, "fp-a", IndexConfig(kind="hnsw")) as m:
            add_range(m, 0, N0)
            m.save(saved)
    return saved


@pytest.mark.parametrize(
    ("mode", "step"),
    [(mode, s) for mode in ("append", "hnsw", "convert") for s in persist.SAVE_STEPS]
    + [("fresh", s) for s in ("dense", "store", "manifest", "committed")],
)
def test_save_killed_at_step_leaves_a_loadable_map(tmp_path: Path, saved: Path, mode, step):
    codec = "f16" if mode == "convert" else CODEC  # the default: p4
    saved = _map_of(mode, saved)
    child = run_child(tmp_path, mode, str(saved), step)
    assert child.wait(timeout=60) == 17  # it really died at that step
    new = list(range(3)) if mode == "fresh" else list(range(N0 + 3))
    with PlaceMap.load(saved, expected_fingerprint="fp-a") as m:
        done = step in persist.SAVE_STEPS[COMMITTED:]
        assert_holds(
            m, new if done else list(range(N0)), codec if mode != "fresh" or not done else CODEC
        )
        add_range(m, len(m), len(m) + 1)  # and the map can be continued and saved again
        m.save(saved)
    with PlaceMap.load(saved) as m:
        assert len(m) == (len(new) if step in persist.SAVE_STEPS[COMMITTED:] else N0) + 1


def test_sigkill_during_repeated_saves(tmp_path: Path, saved: Path) -> None:
    child = run_child(tmp_path, "loop", str(saved), "-", stdout=subprocess.PIPE, text=True)
    reported = [int(child.stdout.readline()) for _ in range(5)]
    os.kill(child.pid, signal.SIGKILL)  # lands anywhere in the next save (or between saves)
    child.wait(timeout=60)
    with PlaceMap.load(saved) as m:
        assert len(m) >= reported[-1]
        assert_holds(m, list(range(len(m))))


TRIALS = """
import os, random, signal, sys, time
import numpy as np
sys.path.insert(0, {test_dir!r})
from test_place_map_persist import add_range, assert_holds
from pair_vpr_ros.place_map import PlaceMap

directory, trials, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
rng = random.Random(seed)


def saving(w):  # continue the map; each completed save is reported (acknowledged)
    m = PlaceMap.load(directory)
    while True:
        n = len(m)
        add_range(m, n, n + 1 + n % 3)
        for i in range(n, len(m)):  # growth rows: committed with their keyframes
            m.growth.add_signature(i, np.full(96, i % 7 / 7.0))
        m.save(directory, checkpoint=n % 2 == 0)  # or folded in later, as the node does
        os.write(w, f"{{len(m)}}\\n".encode())
        if n % 3 == 0:
            m.checkpoint()


def check(acked):  # in a child of its own: this process never opens the map
    try:
        with PlaceMap.load(directory, read_only=True) as m:
            assert len(m) >= acked, (len(m), acked)
            assert_holds(m, list(range(len(m))))
            assert m.growth.counts().signatures == len(m) - 12
        os._exit(0)
    except BaseException as err:
        print("FAILED", repr(err), flush=True)
        os._exit(1)


acked = 12
for trial in range(trials):
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:
        os.close(r)
        saving(w)
    os.close(w)
    reader = os.fdopen(r)
    for _ in range(rng.randrange(0, 3)):  # let 0-2 saves complete, then a random moment
        acked = max(acked, int(reader.readline()))
    time.sleep(rng.uniform(0.0, 0.02))
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    acked = max([acked, *(int(line) for line in reader.read().split())])
    reader.close()
    checker = os.fork()
    if checker == 0:
        check(acked)
    status = os.waitpid(checker, 0)[1]
    print(trial, acked, "ok" if status == 0 else "bad", flush=True)
"""


def test_kill_9_at_random_moments_keeps_every_acknowledged_keyframe(tmp_path, saved) -> None:
    """Issue 48: 40 children continue the map and save it (1-3 keyframes and their growth rows
    a save, the WAL folded in by the save or later), each SIGKILLed at a random moment; after
    each, the map loads and holds every keyframe a completed save acknowledged, as added (the
    first children cross p4's basis fit and the new generation that codes the first 16)."""
    script = tmp_path / "trials.py"
    script.write_text(TRIALS.format(test_dir=str(Path(__file__).parent)))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, str(script), str(saved), "40", "48"], env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    lines = done.stdout.splitlines()
    assert done.returncode == 0, done.stderr[-2000:]
    assert [line.split()[2] for line in lines] == ["ok"] * 40, done.stdout[-2000:]
    assert int(lines[-1].split()[1]) > 40  # saves were acknowledged along the way


class Boom(Exception):
    pass


def _raise_at(step: str):
    def hook(reached: str) -> None:
        if reached == step:
            raise Boom(step)

    return hook


@pytest.mark.parametrize("step", PRE_COMMIT)
@pytest.mark.parametrize("mode", ["append", "clear", "fresh", "save_as"])
def test_failed_save_keeps_the_old_save_and_can_be_retried(
    tmp_path: Path, saved: Path, monkeypatch, mode: str, step: str
) -> None:
    target = tmp_path / "other" if mode == "save_as" else saved
    m = PlaceMap(DIM, SHAPE, "fp-a") if mode == "fresh" else PlaceMap.load(saved)
    if mode == "clear":
        m.clear()
    start = len(m)
    add_range(m, start, start + 2)
    monkeypatch.setattr(persist, "_SAVE_HOOK", _raise_at(step))
    with pytest.raises(Boom):
        m.save(target)
    monkeypatch.setattr(persist, "_SAVE_HOOK", None)
    with PlaceMap.load(saved, read_only=True) as old:
        assert_holds(old, list(range(N0)))
    if mode == "save_as":
        with pytest.raises(MapError, match="manifest.json is missing"):
            PlaceMap.load(target)
    add_range(m, start + 2, start + 3)
    m.save(target)
    m.close()
    with PlaceMap.load(target) as new:
        assert_holds(new, list(range(start + 3)))
    assert sorted(n for n in os.listdir(target) if ".tmp" in n or "work" in n) == []


def test_disk_error_during_save_is_a_map_error(saved: Path, monkeypatch) -> None:
    def fail():
        raise OSError(28, "No space left on device")

    with PlaceMap.load(saved) as m:
        add_range(m, N0, N0 + 1)
        monkeypatch.setattr(m._dense, "sync", fail)
        with pytest.raises(MapError, match=r"saving the place map to .* failed .*No space left"):
            m.save(saved)
        monkeypatch.undo()
        m.save(saved)
    with PlaceMap.load(saved) as m:
        assert_holds(m, list(range(N0 + 1)))
