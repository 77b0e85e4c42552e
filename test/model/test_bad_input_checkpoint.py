"""Bad-input matrix, checkpoints: empty, truncated, foreign, pickle exploits, a damaged `arch`
entry, impossible shapes and non-finite weights each give a CheckpointError naming the file
(test_model_checkpoint.py has the basic cases: missing, text, foreign keys, wrong shapes)."""

from __future__ import annotations

import os
import pickle
import re
import zipfile
from pathlib import Path

import pytest
import torch

from pair_vpr_ros.errors import CheckpointError
from pair_vpr_ros.model import ModelConfig, load_pairvpr, save_pairvpr


@pytest.fixture(scope="module")
def good(tmp_path_factory, tiny_model) -> Path:
    """Our own format (`arch` stored) of a tiny random network."""
    return save_pairvpr(tiny_model, tmp_path_factory.mktemp("w") / "ok.pth")


class Exploit:
    """Unpickling this runs `touch <marker>`: what a hostile .pth would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _cut(good: Path, path: Path, fraction: float) -> None:
    data = good.read_bytes()
    path.write_bytes(data[: max(1, int(len(data) * fraction))])


def _edit(good: Path, path: Path, edit) -> None:
    payload = torch.load(good, weights_only=True)
    edit(payload)
    torch.save(payload, path)


def _set_arch(value):
    return lambda p: p.update(arch=value)


def _arch_field(**fields):
    return lambda p: p["arch"].update(fields)


def _tensor(name: str, value: float):
    def edit(p):
        p["model"][name] = torch.full_like(p["model"][name], value)

    return edit


def _rename_block(p):
    sd = p["model"]
    for key in [k for k in sd if k.startswith("encoder.model.blocks.1.")]:
        sd[key.replace("blocks.1.", "blocks.99999.")] = sd.pop(key)


UNREADABLE = "could not be read as a PyTorch weights file"
CASES = {
    # ---- not a torch file, or not all of one
    "empty": (lambda g, p: p.write_bytes(b""), f"{UNREADABLE} (EOFError: no details)"),
    "one byte": (lambda g, p: _cut(g, p, 0.0), UNREADABLE),
    "cut at 10%": (lambda g, p: _cut(g, p, 0.1), UNREADABLE),
    "cut at 50%": (lambda g, p: _cut(g, p, 0.5), UNREADABLE),
    "cut at 99%": (lambda g, p: _cut(g, p, 0.99), UNREADABLE),
    "folder": (lambda g, p: p.mkdir(), "does not exist (or is not a file)"),
    "zip of text": (
        lambda g, p: zipfile.ZipFile(p, "w").writestr("data.pkl", "hello"),
        UNREADABLE,
    ),
    "random bytes": (lambda g, p: p.write_bytes(os.urandom(4096)), UNREADABLE),
    # ---- pickles that would run code or build objects (weights_only refuses them)
    "torch exploit": (lambda g, p: torch.save(Exploit(p.with_suffix(".pwned")), p), UNREADABLE),
    "plain pickle exploit": (
        lambda g, p: p.write_bytes(pickle.dumps(Exploit(p.with_suffix(".pwned")), protocol=2)),
        UNREADABLE,
    ),
    "object in state_dict": (
        lambda g, p: _edit(g, p, lambda d: d["model"].update(extra=Path("x"))),
        UNREADABLE,
    ),
    # ---- readable, but not weights
    "empty dict": (lambda g, p: torch.save({}, p), "holds a dict, not a state_dict of tensors"),
    "number": (lambda g, p: torch.save(3, p), "holds a int, not a state_dict of tensors"),
    "non-tensor values": (
        lambda g, p: torch.save({"encoder.model.cls_token": 1.0}, p),
        "not a state_dict of tensors",
    ),
    "model is a list": (
        lambda g, p: torch.save({"model": [torch.zeros(1)]}, p),
        "holds a dict, not a state_dict of tensors",
    ),
    # ---- a damaged `arch` entry (issue 13 #6: used to end in a TypeError traceback)
    "arch string": (
        lambda g, p: _edit(g, p, _set_arch("vitb")),
        "stored model config is a str, not a dict of ModelConfig fields; its 'arch' entry is "
        "damaged or not from pair_vpr_ros",
    ),
    "arch number": (lambda g, p: _edit(g, p, _set_arch(7)), "stored model config is a int"),
    "arch list": (lambda g, p: _edit(g, p, _set_arch([1, 2])), "stored model config is a list"),
    "arch unknown field": (
        lambda g, p: _edit(g, p, _arch_field(colour="red")),
        "stored model config has unknown fields ['colour']",
    ),
    "arch field type": (
        lambda g, p: _edit(g, p, _arch_field(embed_dim="32")),
        "stored model config field embed_dim='32' is not int",
    ),
    "arch bool for int": (
        lambda g, p: _edit(g, p, _arch_field(depth=True)),
        "stored model config field depth=True is not int",
    ),
    "arch zero heads": (
        lambda g, p: _edit(g, p, _arch_field(num_heads=0)),
        "stored model config is invalid: encoder width 32 is not divisible by 0 heads",
    ),
    "arch absurd width": (
        lambda g, p: _edit(g, p, _arch_field(embed_dim=1 << 20, num_heads=1)),
        "its stored architecture disagrees with its tensors: embed_dim=1048576 (tensors: 32)",
    ),
    "arch absurd grid": (
        lambda g, p: _edit(g, p, _arch_field(pos_grid=100000)),
        "disagrees with its tensors: pos_grid=100000 (tensors: 4)",
    ),
    # ---- impossible shapes and values
    "block 99999": (
        lambda g, p: _edit(g, p, _rename_block),
        "are numbered up to 99999 but 99998 are missing (e.g. [1, 2, 3])",
    ),
    "pos_embed not square": (
        lambda g, p: _edit(
            g, p, lambda d: d["model"].update({"encoder.model.pos_embed": torch.zeros(1, 8, 32)})
        ),
        "encoder.model.pos_embed holds 7 position rows, not a square grid",
    ),
    # Issue 13 #11: used to load, then fail at the first frame with "descriptor must be finite".
    "all NaN": (
        lambda g, p: _edit(
            g, p, lambda d: d["model"].update({k: v * float("nan") for k, v in d["model"].items()})
        ),
        "holds NaN or infinite values in 97 of 97 tensors",
    ),
    "one inf": (
        lambda g, p: _edit(g, p, _tensor("dec_blocks.1.mlp.fc2.bias", float("inf"))),
        "holds NaN or infinite values in 1 of 97 tensors (e.g. ['dec_blocks.1.mlp.fc2.bias'])",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_checkpoint(tmp_path: Path, good: Path, case: str) -> None:
    make, message = CASES[case]
    path = tmp_path / "bad.pth"
    make(good, path)
    with pytest.raises(CheckpointError, match=re.escape(message)) as info:
        load_pairvpr(path)
    assert str(path) in str(info.value)
    assert not path.with_suffix(".pwned").exists()  # no code ran


def test_the_good_file_loads(good: Path) -> None:
    assert load_pairvpr(good).config == ModelConfig.tiny()
