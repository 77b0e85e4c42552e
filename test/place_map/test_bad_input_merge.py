"""Bad-input matrix, `pairvpr-map` (issue 22 part 3): every bad input is one `error:` line and a
non-zero exit, no input map changes, and no --out folder (or temporary) is left behind."""

from __future__ import annotations

import os

import pytest
from bad_input import saved_map_digest, tree_digest
from map_fixtures import make_map

from pair_vpr_ros.offline.map_cli import main
from pair_vpr_ros.place_map import persist


def _maps(tmp_path):
    return make_map(tmp_path / "a", "r1", "mon", 3, seed=1), make_map(
        tmp_path / "b", "r2", "mon", 2, seed=2
    )


CASES = {
    # name: (extra maps/args builder, exit code, error text)
    "another model": (
        lambda t, a, b: [str(a), str(make_map(t / "x", "r3", "s", 2, 3, fingerprint="model-b"))],
        1,
        "maps of different models cannot be merged: {a} holds model 'model-a' (descriptors 8, "
        "dense tokens [2, 3]), {t}/x holds 'model-b' (descriptors 8, dense tokens [2, 3]): merge "
        "only maps built with the same weights and image size",
    ),
    "another descriptor size": (
        lambda t, a, b: [str(a), str(make_map(t / "x", "r3", "s", 2, 3, dim=16))],
        1,
        "{t}/x holds 'model-a' (descriptors 16, dense tokens [2, 3])",
    ),
    "one map": (lambda t, a, b: [str(a)], 1, "merge needs at least two maps, got 1"),
    "same map twice": (
        lambda t, a, b: [str(a), str(t / "a" / ".." / "a")],
        1,
        "a map is given twice: give each input map once",
    ),
    "missing input": (
        lambda t, a, b: [str(a), str(t / "nowhere")],
        1,
        "input map {t}/nowhere does not exist or is not a folder",
    ),
    "not a map": (
        lambda t, a, b: [str(a), str((t / "empty").mkdir() or t / "empty")],
        1,
        "input map {t}/empty cannot be merged: {t}/empty/manifest.json is missing",
    ),
    "damaged map": (
        lambda t, a, b: [str(a), str(b), (b / "map-1.sqlite").write_bytes(b"x") and str(a)][:2],
        1,
        "input map {b} cannot be merged: keyframe store {b}/map-1.sqlite cannot be read (no such "
        "table: keyframes)",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_merge_is_an_error_line_and_leaves_nothing(tmp_path, capsys, case):
    build, code, message = CASES[case]
    a, b = _maps(tmp_path)
    args = build(tmp_path, a, b)
    before = tree_digest(tmp_path)
    assert main(["merge", *args, "--out", str(tmp_path / "c"), "--quiet"]) == code
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert message.format(t=tmp_path, a=a, b=b) in err
    assert tree_digest(tmp_path) == before and not (tmp_path / "c").exists()


@pytest.mark.parametrize("out", ["existing empty", "existing map", "inside an input", "no parent"])
def test_bad_out_is_refused_before_any_work(tmp_path, capsys, out):
    a, b = _maps(tmp_path)
    target = {
        "existing empty": tmp_path / "c",
        "existing map": a,
        "inside an input": a / "sub",
        "no parent": tmp_path / "none" / "c",
    }[out]
    if out == "existing empty":
        target.mkdir()
    before = tree_digest(tmp_path)
    assert main(["merge", str(a), str(b), "--out", str(target), "--quiet"]) == 1
    err = capsys.readouterr().err
    expected = {
        "existing empty": f"error: --out {target} exists: a merge never writes into an existing "
        "folder; give a new one\n",
        "existing map": f"error: --out {target} exists",
        "inside an input": f"error: --out {target} lies inside an input map",
        "no parent": f"error: --out {target}: its parent folder does not exist",
    }[out]
    assert err.startswith(expected)
    assert tree_digest(tmp_path) == before


@pytest.mark.parametrize("step", ["dense", "index", "store", "manifest"])
def test_a_merge_that_dies_while_saving_leaves_no_out_and_unchanged_inputs(
    tmp_path, capsys, monkeypatch, step
):
    a, b = _maps(tmp_path)
    before = {d: saved_map_digest(d) for d in (a, b)}

    def die(reached: str) -> None:
        if reached == step:
            raise KeyboardInterrupt  # Ctrl-C (or a crash) in the middle of the save

    monkeypatch.setattr(persist, "_SAVE_HOOK", die)
    assert main(["merge", str(a), str(b), "--out", str(tmp_path / "c"), "--quiet"]) == 130
    assert capsys.readouterr().err == "error: interrupted\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]
    assert {d: saved_map_digest(d) for d in (a, b)} == before


def test_info_of_a_missing_or_damaged_map_is_an_error_line(tmp_path, capsys):
    assert main(["info", str(tmp_path / "none")]) == 1
    assert capsys.readouterr().err.startswith(f"error: {tmp_path / 'none'}/manifest.json is")
    a = make_map(tmp_path / "a", "r1", "mon", 2, seed=1)
    (a / "map-1.sqlite").write_bytes(b"x")
    assert main(["info", str(a)]) == 1
    assert "map-1.sqlite cannot be read (no such table: keyframes)" in capsys.readouterr().err


def test_folders_of_a_killed_merge_are_removed_by_the_next(tmp_path, capsys):
    """Issue 38: a merge killed part-way (no clean-up ran) left `.out.merging-PID*` beside
    --out; the next merge into that --out removes them, not those of a merge still running."""
    a, b = _maps(tmp_path)
    dead = 2**22 + 12345  # above Linux's default pid_max: no such process
    for name in (f".out.merging-{dead}", f".out.merging-{dead}.work/pairvpr-map-x"):
        (tmp_path / name).mkdir(parents=True)
        (tmp_path / name / "dense-1.f16").write_bytes(b"half")
    running = tmp_path / f".out.merging-{os.getppid()}"
    running.mkdir()
    assert main(["merge", str(a), str(b), "--out", str(tmp_path / "out")]) == 0
    left = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".out"))
    assert left == [running.name] and (tmp_path / "out" / "manifest.json").is_file()
