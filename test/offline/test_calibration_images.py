"""int8 calibration images from a bag or an image folder (offline/bags/calibration.py): the
picks, the tensor, the wiring into load_model and the OpenVINO cache key."""

from __future__ import annotations

import importlib.util

import cv2
import numpy as np
import pytest
import torch
from bag_fixtures import COMPRESSED, TS2, image_msg, synthetic_images, write_rosbag2

from pair_vpr_ros import weights as weights_module
from pair_vpr_ros.model import ModelConfig, build_pairvpr, preprocess_batch
from pair_vpr_ros.model.calibration import CALIBRATION_IMAGES
from pair_vpr_ros.offline.bags.calibration import (
    calibration_images,
    calibration_loader,
    evenly_spaced,
    skipped_note,
)
from pair_vpr_ros.offline.bags.sources import FrameCounts

SIZE = 28
HAS_OPENVINO = all(importlib.util.find_spec(m) for m in ("openvino", "nncf"))


def write_folder(folder, images, ext=".png"):
    """`images` as files 000.png, 001.png, ... (BGR on disk, as OpenCV writes)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, rgb in enumerate(images):
        cv2.imwrite(str(folder / f"{i:03d}{ext}"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return folder


@pytest.mark.parametrize(
    ("total", "count", "want"),
    [
        (10, 4, [0, 3, 6, 9]),
        (100, 16, [0, 7, 13, 20, 26, 33, 40, 46, 53, 59, 66, 73, 79, 86, 92, 99]),
        (5, 5, [0, 1, 2, 3, 4]),
        (3, 16, [0, 1, 2]),
        (7, 2, [0, 6]),
        (7, 1, [0]),
        (0, 16, []),
    ],
)
def test_evenly_spaced_picks(total, count, want):
    assert evenly_spaced(total, count) == want


def test_folder_source_is_the_picked_images_preprocessed(tmp_path):
    images = synthetic_images(10, size=20, seed=3)
    folder = write_folder(tmp_path / "imgs", images)
    (folder / "notes.txt").write_text("not an image")  # ignored, as the map build does
    counts = FrameCounts()
    got = calibration_images(folder, SIZE, count=4, counts=counts)
    want = preprocess_batch([images[i] for i in (0, 3, 6, 9)], SIZE)
    assert got.shape == (4, 3, SIZE, SIZE) and got.dtype == torch.float32
    assert torch.equal(got, want)
    assert (counts.frames, counts.skipped) == (4, 0)


def test_folder_default_count_and_sorted_names(tmp_path):
    images = synthetic_images(40, size=8, seed=4)
    folder = write_folder(tmp_path / "imgs", images)
    got = calibration_images(folder, SIZE)
    picks = evenly_spaced(40, CALIBRATION_IMAGES)
    assert CALIBRATION_IMAGES == 16 and got.shape[0] == 16
    assert torch.equal(got, preprocess_batch([images[i] for i in picks], SIZE))


@pytest.mark.parametrize("compressed", [False, True])
def test_bag_source_is_the_picked_messages_preprocessed(tmp_path, compressed):
    images = synthetic_images(9, size=24, seed=5)
    bag = write_rosbag2(
        tmp_path / "bag", [(float(i), rgb) for i, rgb in enumerate(images)], compressed=compressed
    )
    counts = FrameCounts()
    got = calibration_images(bag, SIZE, count=3, counts=counts)
    assert torch.equal(got, preprocess_batch([images[i] for i in (0, 4, 8)], SIZE))
    assert (counts.frames, counts.skipped) == (3, 0)


def test_bag_topic_among_several(tmp_path):
    cam, other = synthetic_images(4, size=16, seed=6), synthetic_images(4, size=16, seed=7)
    extra = [("/other", COMPRESSED, image_msg(TS2, i + 0.5, rgb, True), i + 0.5)
             for i, rgb in enumerate(other)]  # fmt: skip
    bag = write_rosbag2(tmp_path / "bag", list(enumerate(cam)), extra=extra)
    got = calibration_images(bag, SIZE, count=2, topic="/other")
    assert torch.equal(got, preprocess_batch([other[0], other[3]], SIZE))


def test_a_bad_pick_is_skipped_counted_and_reported(tmp_path):
    images = synthetic_images(5, size=16, seed=8)
    folder = write_folder(tmp_path / "imgs", images)
    (folder / "002.png").write_bytes(b"not a png")
    counts = FrameCounts()
    got = calibration_images(folder, SIZE, count=5, counts=counts)
    assert torch.equal(got, preprocess_batch([images[i] for i in (0, 1, 3, 4)], SIZE))
    assert (counts.frames, counts.skipped) == (5, 1)
    assert skipped_note(counts, folder) == (
        f"openvino_calibration {folder}: 1 of 5 picked images skipped (first: image file "
        f"{folder / '002.png'}: OpenCV could not decode the data (corrupt, truncated or not an "
        "image)); calibrated on the others"
    )
    assert skipped_note(FrameCounts(frames=5), folder) is None


def test_loader_none_for_synthetic_and_warns_about_skips(tmp_path):
    assert calibration_loader("") is None
    folder = write_folder(tmp_path / "imgs", synthetic_images(3, size=16, seed=9))
    (folder / "001.png").write_bytes(b"")
    notes = []
    load = calibration_loader(str(folder), warn=notes.append, count=3)
    assert load(SIZE).shape == (2, 3, SIZE, SIZE)
    assert len(notes) == 1 and notes[0].startswith(f"openvino_calibration {folder}: 1 of 3")


class Recorder:
    """Stands in for OpenVINOModel: records what load_model passes."""

    calls: list = []

    def __init__(self, model, precision, calibration=None, cache_dir=None, threads=None):
        Recorder.calls.append((precision, calibration))


@pytest.mark.skipif(not HAS_OPENVINO, reason="needs the [openvino] extra")
@pytest.mark.parametrize("precision", ["int8", "fp32"])
def test_load_model_calibrates_int8_only(tmp_path, monkeypatch, precision):
    from pair_vpr_ros.model import openvino_backend

    monkeypatch.setattr(openvino_backend, "OpenVINOModel", Recorder)
    Recorder.calls = []
    sizes = []

    def calibration(size):
        sizes.append(size)
        return torch.zeros(2, 3, size, size)

    weights_module.load_model(
        "random-tiny", backend="openvino", precision=precision, openvino_cache_dir="",
        openvino_calibration=calibration,
    )  # fmt: skip
    size = ModelConfig.tiny().image_size
    assert sizes == ([size] if precision == "int8" else [])
    ((got_precision, images),) = Recorder.calls
    assert got_precision == precision
    assert (
        (images is None)
        if precision == "fp32"
        else torch.equal(images, torch.zeros(2, 3, size, size))
    )


@pytest.mark.skipif(not HAS_OPENVINO, reason="needs the [openvino] extra")
def test_each_calibration_source_has_its_own_cache_entry(tmp_path):
    from pair_vpr_ros.model.calibration import synthetic_calibration
    from pair_vpr_ros.model.openvino_cache import CacheEntry, entry_parts

    model = build_pairvpr(ModelConfig.tiny(), seed=0)
    size = model.config.image_size
    a = write_folder(tmp_path / "a", synthetic_images(4, size=16, seed=10))
    b = write_folder(tmp_path / "b", synthetic_images(4, size=16, seed=11))
    bag = write_rosbag2(tmp_path / "bag", list(enumerate(synthetic_images(4, size=16, seed=10))))
    sources = {
        "synthetic": synthetic_calibration(CALIBRATION_IMAGES, size),
        "folder a": calibration_images(a, size),
        "folder a again": calibration_images(a, size),
        "folder b": calibration_images(b, size),
        "bag of a's images": calibration_images(bag, size),
    }
    keys = {
        name: CacheEntry(tmp_path / "cache", entry_parts(model, "int8", 2, images)).path.name
        for name, images in sources.items()
    }
    assert keys["folder a"] == keys["folder a again"]
    assert keys["bag of a's images"] == keys["folder a"]  # the same pixels, the same graphs
    assert len({keys[n] for n in ("synthetic", "folder a", "folder b")}) == 3


@pytest.mark.slow
@pytest.mark.skipif(not HAS_OPENVINO, reason="needs the [openvino] extra")
def test_int8_model_calibrated_from_a_folder_runs(tmp_path):
    folder = write_folder(tmp_path / "imgs", synthetic_images(6, size=40, seed=12))
    model = weights_module.load_model(
        "random-tiny", backend="openvino", precision="int8", openvino_cache_dir=tmp_path / "c",
        openvino_calibration=calibration_loader(str(folder)),
    )  # fmt: skip
    size = model.config.image_size
    dense, desc = model.encode(preprocess_batch(synthetic_images(2, size=40, seed=13), size))
    assert desc.shape == (2, model.config.desc_dim) and torch.isfinite(desc).all()
    assert model.cache_path is not None and model.cache_path.exists()
    assert np.isfinite(dense.numpy()).all()


@pytest.mark.skipif(not HAS_OPENVINO, reason="needs the [openvino] extra")
@pytest.mark.parametrize("how", ["flags", "params file"])
def test_replay_calibrates_from_the_given_source(tmp_path, monkeypatch, capsys, tiny_model, how):
    """--openvino-calibration[-topic] (else the parameter file's) reach the model loader as
    the images of that source; skipped images become replay warnings."""
    from pair_vpr_ros.offline.replay import run as replay
    from pair_vpr_ros.offline.replay.cli import main

    seen = {}

    def loader(weights, **kwargs):
        seen["images"] = kwargs["openvino_calibration"](SIZE)
        return tiny_model

    monkeypatch.setattr(replay, "load_model", loader)
    cam, other = synthetic_images(3, size=16, seed=14), synthetic_images(3, size=16, seed=15)
    extra = [("/other", COMPRESSED, image_msg(TS2, i + 0.5, rgb, True), i + 0.5)
             for i, rgb in enumerate(other)]  # fmt: skip
    calib = write_rosbag2(tmp_path / "calib", list(enumerate(cam)), extra=extra)
    bag = write_rosbag2(tmp_path / "bag", [(0.0, cam[0]), (1.0, cam[1])])
    folder = write_folder(tmp_path / "imgs", synthetic_images(3, size=16, seed=16))
    (folder / "001.png").write_bytes(b"broken")
    argv = [str(bag), "--weights", "random-tiny", "--out", str(tmp_path / "o"), "--quiet"]
    argv += ["--backend", "openvino", "--precision", "int8"]
    if how == "flags":
        argv += ["--openvino-calibration", str(calib), "--openvino-calibration-topic", "/other"]
        want = preprocess_batch(other, SIZE)
    else:
        params = tmp_path / "p.yaml"
        params.write_text(f"/**:\n  ros__parameters:\n    openvino_calibration: '{folder}'\n")
        argv += ["--params-file", str(params)]
        want = calibration_images(folder, SIZE)
    assert main(argv) == 0
    assert torch.equal(seen["images"], want)
    err = capsys.readouterr().err
    assert ("1 of 3 picked images skipped" in err) == (how == "params file")
