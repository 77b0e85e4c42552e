"""Bad-input matrix, the OpenVINO model cache: a damaged entry (truncated or changed .bin,
garbage .xml, a missing file, a garbage manifest, graphs of other input shapes, a file where the
folder should be) is warned about naming its folder and is not used; the model is built again,
computes what an undamaged one does and replaces the entry. A cache folder that cannot be
written: a warning, and the model runs without it. Skipped without OpenVINO."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import pytest
import torch
from extras import require

require("openvino")
import numpy as np  # noqa: E402
import openvino as ov  # noqa: E402
import openvino.opset13 as ops  # noqa: E402

from pair_vpr_ros.model.export import example_inputs  # noqa: E402
from pair_vpr_ros.model.openvino_backend import OpenVINOModel  # noqa: E402
from pair_vpr_ros.model.openvino_cache import MANIFEST, CacheEntry, _file_digest  # noqa: E402

LOGGER = "pair_vpr_ros.openvino_cache"


@pytest.fixture(scope="module")
def good(tiny_model, tmp_path_factory) -> OpenVINOModel:
    """A model whose cache entry was just written (copied, then damaged, by each case)."""
    return OpenVINOModel(tiny_model, "fp32", cache_dir=tmp_path_factory.mktemp("ovcache"))


def _rewrite_manifest(entry: Path) -> None:
    """Make the manifest agree with the files again: only the deeper checks can tell."""
    manifest = json.loads((entry / MANIFEST).read_text())
    for name in manifest["files"]:
        manifest["files"][name] = {
            "size": (entry / name).stat().st_size,
            "sha256": _file_digest(entry / name),
        }
    (entry / MANIFEST).write_text(json.dumps(manifest))


def _truncate(entry: Path) -> None:
    data = (entry / "encoder.bin").read_bytes()
    (entry / "encoder.bin").write_bytes(data[: len(data) // 2])


def _flip_byte(entry: Path) -> None:
    """Same size, one weight byte changed: only the sha256 tells."""
    data = bytearray((entry / "chunk.bin").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (entry / "chunk.bin").write_bytes(bytes(data))


def _other_shapes(entry: Path) -> None:
    """A valid graph of 70 px images (two outputs, as the encoder's) in place of the encoder."""
    image = ops.parameter([1, 3, 70, 70], np.float32)
    graph = ov.Model([ops.relu(image), ops.sigmoid(image)], [image])
    ov.save_model(graph, entry / "encoder.xml", compress_to_fp16=False)
    _rewrite_manifest(entry)


def _entry_is_a_file(entry: Path) -> None:
    shutil.rmtree(entry)
    entry.write_bytes(b"not a folder")


def _other_parts(entry: Path) -> None:
    manifest = json.loads((entry / MANIFEST).read_text())
    manifest["parts"]["precision"] = "int8"
    (entry / MANIFEST).write_text(json.dumps(manifest))


DAMAGE = {
    "truncated bin": (_truncate, "encoder.bin is not the file that was saved"),
    "changed bin byte": (_flip_byte, "chunk.bin is not the file that was saved"),
    "garbage xml": (
        lambda e: ((e / "query.xml").write_bytes(b"<net><<garbage"), _rewrite_manifest(e)),
        "",
    ),
    "missing bin": (lambda e: (e / "query.bin").unlink(), "query.bin"),
    "missing manifest": (lambda e: (e / MANIFEST).unlink(), MANIFEST),
    "garbage manifest": (lambda e: (e / MANIFEST).write_bytes(b"\x00{]"), ""),
    "manifest of a list": (lambda e: (e / MANIFEST).write_text("[1, 2]"), ""),
    "manifest of other inputs": (_other_parts, "manifest.json was written for other inputs"),
    "other input shapes": (_other_shapes, "encoder graph has inputs [(1, 3, 70, 70)]"),
    "entry is a file": (_entry_is_a_file, ""),
}


def _damaged_copy(good: OpenVINOModel, root: Path, damage) -> Path:
    shutil.copytree(good.cache_path.parent, root, dirs_exist_ok=True)
    damage(root / good.cache_path.name)
    return root / good.cache_path.name


@pytest.mark.parametrize("case", list(DAMAGE))
def test_damaged_entry_is_not_used(tiny_model, good, tmp_path, caplog, case):
    damage, reason = DAMAGE[case]
    entry_path = _damaged_copy(good, tmp_path, damage)
    entry = CacheEntry(tmp_path, json.loads((good.cache_path / MANIFEST).read_text())["parts"])
    assert entry.path == entry_path
    shapes = {k: [tuple(x.shape) for x in v] for k, v in example_inputs(tiny_model, 2).items()}
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        assert entry.load(ov, shapes) is None
    (record,) = caplog.records
    assert f"OpenVINO cache entry {entry_path} is damaged (" in record.getMessage()
    assert reason in record.getMessage()
    assert "building the model again" in record.getMessage()


def test_damaged_entry_is_rebuilt_and_replaced(tiny_model, good, tmp_path, caplog):
    entry = _damaged_copy(good, tmp_path, _flip_byte)
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        model = OpenVINOModel(tiny_model, "fp32", cache_dir=tmp_path)
    assert not model.from_cache and model.cache_path == entry
    assert str(entry) in caplog.text
    images = torch.zeros(1, 3, 56, 56)
    for got, want in zip(model.encode(images), good.encode(images), strict=True):
        assert torch.equal(got, want)
    caplog.clear()
    again = OpenVINOModel(tiny_model, "fp32", cache_dir=tmp_path)
    assert again.from_cache and not caplog.records
    assert sorted(p.name for p in tmp_path.iterdir()) == [entry.name]  # nothing left over


def _under_a_file(root: Path) -> Path:
    (root / "file").write_text("x")
    return root / "file" / "cache"


def _a_file(root: Path) -> Path:
    (root / "cache").write_text("x")
    return root / "cache"


UNWRITABLE = {"under a file": _under_a_file, "is a file": _a_file}


@pytest.mark.parametrize(
    "case",
    [pytest.param(c, marks=[pytest.mark.slow] if c == "is a file" else []) for c in UNWRITABLE],
)
def test_unwritable_cache_folder_runs_without_it(tiny_model, tmp_path, caplog, case):
    folder = UNWRITABLE[case](tmp_path)
    before = sorted(tmp_path.rglob("*"))
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        model = OpenVINOModel(tiny_model, "fp32", cache_dir=folder)
    assert not model.from_cache
    assert f"cannot write the OpenVINO cache at {folder} (" in caplog.text
    assert "running without it" in caplog.text
    assert model.encode(torch.zeros(1, 3, 56, 56))[1].shape == (1, tiny_model.config.desc_dim)
    assert sorted(tmp_path.rglob("*")) == before
