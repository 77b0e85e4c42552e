"""The OpenVINO model cache: a second start reads the graphs instead of exporting (and
quantizing) again and computes the same bits; every input of the graphs has its own entry; no
cache, nothing written. Damaged entries and unwritable folders: test_bad_input_openvino_cache.py.
Skipped without the optional packages."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from extras import require

from pair_vpr_ros.model import ModelConfig, build_pairvpr
from pair_vpr_ros.model.calibration import synthetic_calibration
from pair_vpr_ros.weights import load_model

require("openvino")
from pair_vpr_ros.model import openvino_backend, openvino_cache  # noqa: E402
from pair_vpr_ros.model.openvino_backend import OpenVINOModel  # noqa: E402
from pair_vpr_ros.model.openvino_cache import (  # noqa: E402
    CacheEntry,
    entry_parts,
    resolve_cache_dir,
    user_cache_dir,
)


def outputs(model) -> tuple[torch.Tensor, ...]:
    """Dense tokens, descriptors and pair scores of 3 fixed images (one padded chunk)."""
    images = synthetic_calibration(3, model.config.image_size, seed=100)
    dense, desc = model.encode(images)
    return dense, desc, model.pair_scores(dense[0], dense)


def refuse(name: str):
    def fail(*args, **kwargs):
        raise AssertionError(f"{name} ran: the graphs were not read from the cache")

    return fail


def files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


def test_second_start_reads_the_cache(tiny_model, tmp_path, monkeypatch):
    first = OpenVINOModel(tiny_model, "fp32", cache_dir=tmp_path)
    assert not first.from_cache and first.cache_path.parent == tmp_path
    names = {"encoder", "query", "chunk", "chunk_query", "chunk_candidate"}
    assert files(tmp_path) == sorted(
        [f"{first.cache_path.name}/manifest.json"]
        + [f"{first.cache_path.name}/{n}{s}" for n in names for s in (".bin", ".xml")]
    )
    monkeypatch.setattr(openvino_backend, "build_graphs", refuse("export"))
    second = OpenVINOModel(tiny_model, "fp32", cache_dir=tmp_path)
    assert second.from_cache and second.cache_path == first.cache_path
    for got, want in zip(outputs(second), outputs(first), strict=True):
        assert torch.equal(got, want)
    # and the same numbers as without a cache (f32 weights are stored as f32, not f16)
    monkeypatch.undo()
    for got, want in zip(outputs(second), outputs(OpenVINOModel(tiny_model)), strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-6)


@pytest.mark.slow
def test_int8_second_start_skips_calibration(tiny_model, tmp_path, monkeypatch):
    require("nncf")
    calibration = synthetic_calibration(4, 56)
    first = OpenVINOModel(tiny_model, "int8", calibration=calibration, cache_dir=tmp_path)
    monkeypatch.setattr(openvino_backend, "quantize", refuse("quantize"))
    second = OpenVINOModel(tiny_model, "int8", calibration=calibration, cache_dir=tmp_path)
    assert (first.from_cache, second.from_cache) == (False, True)
    assert second.fingerprint == first.fingerprint and "+ov-int8" in second.fingerprint
    for got, want in zip(outputs(second), outputs(first), strict=True):
        assert torch.equal(got, want)
    # other calibration images: another entry, calibrated again
    with pytest.raises(AssertionError, match="quantize ran"):
        OpenVINOModel(tiny_model, "int8", calibration=calibration[:3], cache_dir=tmp_path)


def test_every_input_of_the_graphs_has_its_own_entry(tiny_model, tmp_path):
    require("nncf")
    images = synthetic_calibration(4, 56)

    def key(model=tiny_model, precision="int8", chunk=2, calibration=images) -> str:
        return CacheEntry(tmp_path, entry_parts(model, precision, chunk, calibration)).path.name

    other_weights = build_pairvpr(ModelConfig.tiny(), seed=0)
    with torch.no_grad():
        other_weights.globalizer[0].bias.add_(1e-3)  # same weights_id, other weights
    keys = [
        key(),
        key(precision="fp32", calibration=None),
        key(precision="bf16", calibration=None),
        key(chunk=3),
        key(calibration=images[:3]),
        key(calibration=images + 1e-3),
        key(model=other_weights),
        key(model=build_pairvpr(ModelConfig.tiny(image_size=70), seed=0)),
    ]
    assert len(set(keys)) == len(keys)
    assert key() == key(model=build_pairvpr(ModelConfig.tiny(), seed=0))  # same weights
    assert key(precision="fp32", calibration=None) == key(precision="fp32", calibration=images)
    parts = entry_parts(tiny_model, "int8", 2, images)
    assert {"cache_version", "openvino", "nncf", "torch", "calibration"} <= set(parts)
    versions = dict(parts, cache_version=str(openvino_cache.CACHE_VERSION + 1))
    assert CacheEntry(tmp_path, versions).path.name != key()


def test_no_cache_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.chdir(tmp_path)
    model = load_model("random-tiny", backend="openvino", openvino_cache_dir="")
    assert not model.from_cache and model.cache_path is None
    assert files(tmp_path) == []
    model = load_model("random-tiny", backend="openvino")  # default: the per-user folder
    assert model.cache_path.parent == tmp_path / "xdg" / "pair_vpr_ros" / "openvino"
    assert (model.cache_path / "manifest.json").is_file()


def test_where_the_cache_lives(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert user_cache_dir() == tmp_path / "pair_vpr_ros" / "openvino"
    assert resolve_cache_dir("auto") == user_cache_dir()
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    for ignored in ("relative/cache", ""):  # the XDG spec: absolute paths only
        monkeypatch.setenv("XDG_CACHE_HOME", ignored)
        assert user_cache_dir() == tmp_path / "home" / ".cache" / "pair_vpr_ros" / "openvino"
    assert resolve_cache_dir("") is None and resolve_cache_dir(None) is None
    assert resolve_cache_dir("~/ov") == tmp_path / "home" / "ov"
    assert resolve_cache_dir(tmp_path / "x") == tmp_path / "x"


@pytest.mark.slow
def test_a_killed_writer_leaves_no_entry(tiny_model, tmp_path):
    """A writer killed before its rename leaves only a temporary folder: the entry is built
    again, and the leftover is removed once it is an hour old."""
    first = OpenVINOModel(tiny_model, "fp32", cache_dir=tmp_path)
    leftover = tmp_path / f".{first.cache_path.name}.killed"
    first.cache_path.rename(leftover)
    (leftover / "encoder.bin").unlink()
    (leftover / "encoder.bin").write_bytes(b"half")
    again = OpenVINOModel(tiny_model, "fp32", cache_dir=tmp_path)
    assert not again.from_cache and (again.cache_path / "manifest.json").is_file()
    openvino_cache._remove_stale_temps(tmp_path)
    assert leftover.exists()  # it may be another process still writing
    hour_ago = leftover.stat().st_mtime - openvino_cache.STALE_TEMP_S - 1
    os.utime(leftover, (hour_ago, hour_ago))
    openvino_cache._remove_stale_temps(tmp_path)  # what the next save does first
    assert [p.name for p in tmp_path.iterdir()] == [again.cache_path.name]
