"""Bad-input matrix, `pairvpr-bag-replay` command line: every numeric flag, parameter files,
output folders (a file, read-only, disk full at each write) and map folders (an existing map,
another model's, a folder of other files, a map open elsewhere). Each case checks the exit code,
the `error:` line and that no saved map changed."""

from __future__ import annotations

import errno
import importlib.util
import json
import os
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
from bad_input import tree_digest
from bag_fixtures import TS2, image_msg, synthetic_images, write_rosbag2

from pair_vpr_ros.model import ModelConfig, build_pairvpr, save_pairvpr
from pair_vpr_ros.offline.replay import run as replay
from pair_vpr_ros.offline.replay.cli import main
from pair_vpr_ros.place_map import PlaceMap

FRAMES, KEYFRAMES = 4, 1


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A 4-frame bag with poses, tiny weights, and the map a first replay saved (random-init
    descriptors of these images are near-identical: it holds 1 keyframe)."""
    root = tmp_path_factory.mktemp("replay")
    torch.manual_seed(0)
    weights = save_pairvpr(build_pairvpr(ModelConfig.tiny()), root / "tiny.pth")
    images = [(float(i), rgb) for i, rgb in enumerate(synthetic_images(FRAMES, size=16))]
    poses = [(float(i), (float(i), 0.0, 0.0)) for i in range(FRAMES)]
    bag = write_rosbag2(root / "bag", images, poses)
    assert (
        main([str(bag), "--weights", str(weights), "--out", str(root / "first"), "--quiet"]) == 0
    )
    return bag, weights, root / "first" / "map"


def run(setup, tmp_path, *extra: str, out: Path | None = None) -> int:
    bag, weights, _ = setup
    out = tmp_path / "out" if out is None else out
    return main([str(bag), "--weights", str(weights), "--out", str(out), "--quiet", *extra])


FLAG_CASES = {
    "gt-radius negative": (["--gt-radius", "-5"], "argument --gt-radius: must be a finite number"),
    "gt-radius nan": (["--gt-radius", "nan"], "of metres > 0, got 'nan'"),
    "gt-radius inf": (["--gt-radius", "inf"], "of metres > 0, got 'inf'"),
    "gt-radius zero": (["--gt-radius", "0"], "of metres > 0, got '0'"),
    "gt-radius text": (["--gt-radius", "ten"], "of metres > 0, got 'ten'"),
    "threshold nan": (["--threshold", "nan"], "argument --threshold: must be a finite number"),
    "threshold -inf": (["--threshold=-inf"], "must be a finite number, got '-inf'"),
    "top-k zero": (["--top-k", "0"], "argument --top-k: must be an integer >= 1, got 0"),
    "top-k negative": (["--top-k", "-3"], "must be an integer >= 1, got -3"),
    "top-k fraction": (["--top-k", "1.5"], "must be an integer >= 1, got '1.5'"),
    "budget negative": (
        ["--rerank-budget-ms=-5"],
        "argument --rerank-budget-ms: rerank_budget_ms=-5.0 is out of range [0.0, 600000.0]",
    ),
    "budget nan": (["--rerank-budget-ms", "nan"], "rerank_budget_ms must be a finite number"),
    "budget text": (
        ["--rerank-budget-ms", "fast"],
        "argument --rerank-budget-ms: rerank_budget_ms must be a number, got 'fast'",
    ),
    "global-weight negative": (
        ["--global-weight=-1"],
        "argument --global-weight: global_weight=-1.0 is out of range [0.0, 10000.0]",
    ),
    "global-weight nan": (["--global-weight", "nan"], "global_weight must be a finite number"),
    "global-weight text": (
        ["--global-weight", "some"],
        "argument --global-weight: global_weight must be a number, got 'some'",
    ),
    "budget too large": (["--rerank-budget-ms", "1e9"], "is out of range [0.0, 600000.0]"),
    "batch-size zero": (["--batch-size", "0"], "argument --batch-size: must be an integer >= 1"),
    "max-frames zero": (["--max-frames", "0"], "argument --max-frames: must be an integer >= 1"),
    "unknown flag": (["--radius", "3"], "unrecognized arguments: --radius 3"),
    "backend typo": (["--backend", "openvno"], "argument --backend: invalid choice: 'openvno'"),
    "precision typo": (["--precision", "int4"], "argument --precision: invalid choice: 'int4'"),
    "robot id with a space": (
        ["--robot-id", "my robot"],
        "argument --robot-id: robot_id 'my robot' must be 1-64 characters of ASCII letters, "
        "digits or '_' (a robot id starts with a letter): it names folders, a ROS topic and "
        "pose-graph keys, e.g. robot1",
    ),
    "robot id '..'": (["--robot-id", ".."], "argument --robot-id: robot_id '..' must be 1-64"),
    "session id 'a.b'": (["--session-id", "a.b"], "argument --session-id: session_id 'a.b' must"),
    "session id empty": (["--session-id", ""], "argument --session-id: session_id '' must be"),
    "session id with a colon": (
        ["--session-id", "2026-11-25T09:30"],
        "session_id '2026-11-25T09:30' must be 1-64 characters",
    ),
}


@pytest.mark.parametrize("case", list(FLAG_CASES))
def test_bad_flag_is_a_usage_error(setup, tmp_path, capsys, case) -> None:
    args, message = FLAG_CASES[case]
    assert run(setup, tmp_path, *args) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # nothing started


PARAMS_CASES = {
    "binary": (b"\x89PNG\r\n\x1a\n\xff", "is not a text (UTF-8) file"),
    "top-level list": (b"- top_k\n- 3\n", "holds a list at the top level"),
    "top-level string": (b"top_k=3\n", "holds a str at the top level"),
    "list under ros__parameters": (
        b"/**:\n  ros__parameters:\n    - top_k: 3\n",
        "ros__parameters holds a list, not a mapping",
    ),
    "key given twice": (  # issue 25 #6: the last value won without a word
        b"/**:\n  ros__parameters:\n    top_k: 3\n    top_k: 20\n",
        "'top_k' is given twice (lines 3 and 4): keep one (YAML would use the last one without "
        "a word)",
    ),
}


@pytest.mark.parametrize("case", list(PARAMS_CASES))
def test_bad_params_file_is_an_error_line(setup, tmp_path, capsys, case) -> None:
    content, message = PARAMS_CASES[case]
    params = tmp_path / "p.yaml"
    params.write_bytes(content)
    assert run(setup, tmp_path, "--params-file", str(params)) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: parameter file {params}") and message in err
    assert err.count("\n") == 1


@pytest.mark.parametrize("how", ["flag", "params file"])
def test_backend_without_its_package_is_an_error_line(setup, tmp_path, capsys, how, monkeypatch):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "nncf" else find_spec(name)
    )
    extra = ["--backend", "openvino", "--precision", "int8"]
    if how == "params file":
        params = tmp_path / "p.yaml"
        params.write_text("/**:\n  ros__parameters:\n    backend: openvino\n    precision: int8\n")
        extra = ["--params-file", str(params)]
    assert run(setup, tmp_path, *extra) == 1
    err = capsys.readouterr().err
    assert err == (
        "error: backend openvino needs the package 'nncf', which is not installed: pip install "
        "'pair_vpr_ros[openvino]' (make setup installs it), or use backend torch\n"
    )
    assert not (tmp_path / "out").exists()  # refused before anything was written


# ---- output folders


def test_out_is_a_file(setup, tmp_path, capsys) -> None:
    (tmp_path / "out").write_text("precious")
    assert run(setup, tmp_path) == 1
    assert capsys.readouterr().err == (
        f"error: output folder {tmp_path / 'out'} is not a folder: give a folder\n"
    )
    assert (tmp_path / "out").read_text() == "precious"


def test_out_below_a_file(setup, tmp_path, capsys) -> None:
    (tmp_path / "file").write_text("x")
    assert run(setup, tmp_path, out=tmp_path / "file" / "out") == 1
    assert capsys.readouterr().err == (
        f"error: output folder {tmp_path / 'file' / 'out'} is not a folder ({tmp_path / 'file'} "
        "is a file): give a folder\n"
    )


def test_read_only_out(setup, tmp_path, capsys, monkeypatch) -> None:
    def read_only(*_args, **_kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)  # tests run as root: simulate
    assert run(setup, tmp_path) == 1
    assert capsys.readouterr().err == (
        f"error: cannot write output folder {tmp_path / 'out'}: {tmp_path} is not writable "
        "(Read-only file system); pick a writable folder\n"
    )


def _disk_full(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_disk_full_writing_the_report(setup, tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setattr(replay, "write_report", _disk_full)
    assert run(setup, tmp_path) == 1
    err = capsys.readouterr().err
    assert err.endswith(
        f"error: writing the report to {tmp_path / 'out'} failed: [Errno 28] No space left on "
        "device (what was processed before is written)\n"
    )
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert saved["error"].startswith("writing the report") and saved["frames"] == FRAMES
    with PlaceMap.load(tmp_path / "out" / "map") as m:  # the map was saved before
        assert len(m) == saved["keyframes"] == KEYFRAMES


def test_disk_full_writing_the_summary(setup, tmp_path, capsys, monkeypatch) -> None:
    real = Path.write_text

    def full(self, *args, **kwargs):
        if self.name == "summary.json":
            _disk_full()
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full)
    assert run(setup, tmp_path) == 1
    assert capsys.readouterr().err == (
        f"error: cannot write {tmp_path / 'out' / 'summary.json'} (No space left on device); "
        f"the map is saved in {(tmp_path / 'out' / 'map').resolve()}\n"
    )


def test_disk_full_writing_the_output_bag(setup, tmp_path, capsys, monkeypatch) -> None:
    from rosbags.rosbag2 import Writer

    calls = []

    def full_after_two(self, *args, **kwargs):
        calls.append(1)
        if len(calls) > 2:
            _disk_full()

    monkeypatch.setattr(Writer, "write", full_after_two)
    assert run(setup, tmp_path, "--write-bag") == 1
    err = capsys.readouterr().err
    assert re.search(r"error: stopped after \d image messages: writing the output bag ", err)
    assert "failed (No space left on device); free disk space or write elsewhere" in err
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert re.match(r"stopped after \d image messages", saved["error"])


# ---- map folders (issue 13 #3: an existing map used to be replaced silently)


def test_existing_map_is_refused_and_unchanged(setup, tmp_path, capsys) -> None:
    _, _, saved = setup
    before = tree_digest(saved)
    assert run(setup, tmp_path, "--map-dir", str(saved)) == 1
    err = capsys.readouterr().err
    assert err.startswith(
        f"error: map folder {saved} holds a saved place map ({KEYFRAMES} keyframes"
    )
    assert err.endswith(
        "that this replay would replace: pass --overwrite to replace it, or --map-dir "
        "NEW_FOLDER (to add to a map, load it in vpr_node and play the bag)\n"
    )
    assert tree_digest(saved) == before and not (tmp_path / "out").exists()


def test_existing_map_of_another_model_is_refused(setup, tmp_path, capsys) -> None:
    bag, _, saved = setup
    other = save_pairvpr(build_pairvpr(ModelConfig.tiny(), seed=3), tmp_path / "other.pth")
    before = tree_digest(saved)
    args = [str(bag), "--weights", str(other), "--out", str(tmp_path / "o"), "--quiet"]
    assert main([*args, "--map-dir", str(saved)]) == 1
    assert "holds a saved place map" in capsys.readouterr().err
    assert tree_digest(saved) == before


def test_rerun_into_the_same_out_needs_overwrite(setup, tmp_path, capsys) -> None:
    assert run(setup, tmp_path) == 0
    before = tree_digest(tmp_path / "out" / "map")
    assert run(setup, tmp_path) == 1
    assert "holds a saved place map" in capsys.readouterr().err
    assert tree_digest(tmp_path / "out" / "map") == before
    assert run(setup, tmp_path, "--overwrite") == 0
    with PlaceMap.load(tmp_path / "out" / "map") as m:
        assert len(m) == KEYFRAMES


def test_map_folder_of_other_files(setup, tmp_path, capsys) -> None:
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "holiday.jpg").write_bytes(b"jpeg")
    assert run(setup, tmp_path, "--map-dir", str(folder)) == 1
    assert capsys.readouterr().err == (
        f"error: map folder {folder} holds other files and no saved map: give a new or empty "
        "folder (or pass --overwrite to save the map beside them)\n"
    )
    assert sorted(p.name for p in folder.iterdir()) == ["holiday.jpg"]


def test_map_folder_is_a_file(setup, tmp_path, capsys) -> None:
    (tmp_path / "map").write_text("x")
    assert run(setup, tmp_path, "--map-dir", str(tmp_path / "map")) == 1
    assert capsys.readouterr().err == (
        f"error: map folder {tmp_path / 'map'} is not a folder: give a folder\n"
    )


def test_map_open_for_writing_elsewhere_is_refused_before_the_run(setup, tmp_path, capsys):
    _, _, saved = setup
    copy = tmp_path / "copy"
    with PlaceMap.load(saved) as m:
        m.save(copy)  # this PlaceMap now holds copy's writer lock
        before = tree_digest(copy)
        assert run(setup, tmp_path, "--map-dir", str(copy), "--overwrite") == 1
        err = capsys.readouterr().err
        assert tree_digest(copy) == before  # (closing the writer folds its WAL: checked before)
    assert err == (  # issue 48: the replay's own advice, not the library's
        f"error: map folder {copy} is being written by another process (pid {os.getpid()}): "
        "wait until it ends (another replay, or a vpr_node with this map_dir), or give another "
        "--map-dir\n"
    )
    assert not (tmp_path / "out").exists()


def test_a_second_replay_into_the_same_map_folder_is_refused_at_its_start(setup, tmp_path, capsys):
    """Issue 48: a replay holds its map folder from its start (before: only its save took the
    lock, so a second replay into the same new folder ran its whole bag first)."""
    from pair_vpr_ros.offline.replay.outputs import check_map_dir

    first = check_map_dir(tmp_path / "shared", overwrite=False)  # a first replay, running
    try:
        assert (tmp_path / "shared").is_dir()
        assert run(setup, tmp_path, "--map-dir", str(tmp_path / "shared")) == 1
        assert capsys.readouterr().err.startswith(
            f"error: map folder {tmp_path / 'shared'} is being written by another process (pid "
        )
        assert not (tmp_path / "out").exists()  # refused before the bag was read
    finally:
        first.release()
    assert not (tmp_path / "shared").exists()  # made for the first one, which saved nothing


@pytest.mark.parametrize("how", ["flag", "params file"])
def test_images_over_the_pixel_limit_are_counted_skips(setup, tmp_path, capsys, how) -> None:
    """Issue 13 #10: the limit is configurable; 16 x 16 images over a 100-pixel limit."""
    if how == "flag":
        extra = ["--max-image-pixels", "100"]
    else:
        params = tmp_path / "p.yaml"
        params.write_text("/**:\n  ros__parameters:\n    max_image_pixels: 100\n")
        extra = ["--params-file", str(params)]
    assert run(setup, tmp_path, *extra) == 0
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert (saved["frames"], saved["skipped"], saved["keyframes"]) == (FRAMES, FRAMES, 0)
    (reason,) = saved["skip_reasons"]
    assert reason.endswith(
        "the image is 16 x 16 = 256 pixels, more than the limit of 100 (max_image_pixels): "
        "skipped; raise the limit if the camera really sends images this large"
    )
    assert (
        f"warning: no image of /cam/image could be used, e.g.: {reason}" in capsys.readouterr().err
    )


def test_a_1_by_20000_mono8_strip_replays_with_outputs(setup, tmp_path, capsys) -> None:
    """Issue 25 #6: such images ended the replay with a cv2 traceback in the keyframe-feature
    step (scaled height 0) and nothing written; now they are encoded, and get no features."""
    _, weights, _ = setup
    rng = np.random.default_rng(0)
    grey = [rng.integers(0, 256, (1, 20000), dtype=np.uint8) for _ in range(3)]
    extra = [
        ("/cam/image", "sensor_msgs/msg/Image",
         image_msg(TS2, float(i), np.repeat(g[..., None], 3, 2), False, encoding="mono8",
                   step=20000, data=g.reshape(-1).copy()), float(i))
        for i, g in enumerate(grey)
    ]  # fmt: skip
    bag = write_rosbag2(tmp_path / "strip", [], extra=extra)
    out = tmp_path / "out"
    code = main([str(bag), "--weights", str(weights), "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr().err
    saved = json.loads((out / "summary.json").read_text())
    assert (saved["frames"], saved["skipped"]) == (3, 0)
    assert saved["keyframes"] >= 1 and (out / "loops.json").is_file() and (out / "map").is_dir()


def test_a_wrong_bag_path_is_said_before_the_weights_search(tmp_path, capsys, monkeypatch):
    """Issue 25 #5: with no weights anywhere, a mistyped bag path was reported as missing
    weights; the bag is checked first now."""
    monkeypatch.delenv("PAIRVPR_WEIGHTS", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "no-weights-here"))
    missing = tmp_path / "recording.mcap"
    assert main([str(missing), "--out", str(tmp_path / "out"), "--quiet"]) == 1
    assert capsys.readouterr().err == (
        f"error: bag {missing} does not exist: give a rosbag2 folder, a .mcap or .db3 file or "
        "a ROS 1 .bag\n"
    )
    assert not (tmp_path / "out").exists()
