"""weights: one resolution (explicit, PAIRVPR_WEIGHTS, params file, per-user folder) and one
loader for the node, the replay and the evaluation."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch

from pair_vpr_ros.errors import CheckpointError, ConfigError
from pair_vpr_ros.model import ModelConfig, build_pairvpr, save_pairvpr
from pair_vpr_ros.weights import (
    ENV_VAR,
    RELEASED,
    Weights,
    check_runtime,
    load_model,
    resolve_weights,
)

# test/conftest.py unsets PAIRVPR_WEIGHTS and points XDG_DATA_HOME at a folder that never exists.


@pytest.fixture
def user_dir(tmp_path, monkeypatch) -> Path:
    """An empty per-user data folder ($XDG_DATA_HOME/pair_vpr_ros)."""
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    folder = tmp_path / "xdg" / "pair_vpr_ros"
    folder.mkdir(parents=True)
    return folder


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    model = build_pairvpr(ModelConfig.tiny(), seed=0)
    return save_pairvpr(model, tmp_path_factory.mktemp("w") / "tiny.pth")


def _params(path: Path, weights: str | None) -> Path:
    entry = f"    weights: {weights!r}\n" if weights is not None else "    top_k: 3\n"
    path.write_text("/**:\n  ros__parameters:\n" + entry)
    return path


def test_first_match_wins(tmp_path, user_dir, monkeypatch):
    (user_dir / "mine.pth").write_bytes(b"")
    params = _params(tmp_path / "p.yaml", "from_params.pth")
    monkeypatch.setenv(ENV_VAR, "from_env.pth")
    assert resolve_weights("given.pth", params) == Weights("given.pth", "--weights")
    assert resolve_weights(None, params) == Weights("from_env.pth", f"${ENV_VAR}")
    monkeypatch.delenv(ENV_VAR)
    assert resolve_weights(None, params) == Weights("from_params.pth", f"'weights' in {params}")
    assert resolve_weights("", _params(tmp_path / "q.yaml", "")) == Weights(
        str(user_dir / "mine.pth"), f"the one .pth in {user_dir}"
    )
    assert resolve_weights(None, _params(tmp_path / "r.yaml", None)).value == str(
        user_dir / "mine.pth"
    )


def test_default_user_folder_without_xdg(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    folder = tmp_path / ".local" / "share" / "pair_vpr_ros"
    folder.mkdir(parents=True)
    (folder / "vitB.pth").write_bytes(b"")
    (folder / "notes.txt").write_text("not weights")
    for xdg in ("", "relative/path"):  # unset or relative: the XDG spec's default
        monkeypatch.setenv("XDG_DATA_HOME", xdg)
        assert resolve_weights().value == str(folder / "vitB.pth")
    monkeypatch.delenv("XDG_DATA_HOME")
    assert resolve_weights().value == str(folder / "vitB.pth")


def test_nothing_anywhere_names_every_place(tmp_path, monkeypatch):
    folder = tmp_path / "xdg" / "pair_vpr_ros"
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    with pytest.raises(CheckpointError) as caught:
        resolve_weights()
    assert str(caught.value) == (
        f"no Pair-VPR weights found; looked in --weights: not given; ${ENV_VAR}: not set; "
        f"'weights' in a --params-file: none given; {folder}: no such folder. Set one of these "
        f"to a checkpoint (.pth) or put exactly one .pth into {folder}; {RELEASED}"
    )
    folder.mkdir(parents=True)
    params = _params(tmp_path / "p.yaml", "")
    with pytest.raises(CheckpointError, match=f"'weights' in {params}: not set; {folder}: no "):
        resolve_weights(None, params)
    with pytest.raises(CheckpointError) as caught:  # the node: ROS merged its params file
        resolve_weights("", explicit_name="parameter weights", params_rule=False)
    assert str(caught.value).startswith(
        f"no Pair-VPR weights found; looked in parameter weights: not given; ${ENV_VAR}: not "
        f"set; {folder}: no .pth file. Set one"
    )
    assert "CSIRORobotics/Pair-VPR" in RELEASED and "pairvpr-vitB.pth" in RELEASED


def test_several_in_the_user_folder_is_an_error(user_dir):
    (user_dir / "b.pth").write_bytes(b"")
    (user_dir / "a.pth").write_bytes(b"")
    with pytest.raises(CheckpointError) as caught:
        resolve_weights()
    assert str(caught.value) == (
        f"{user_dir} holds 2 .pth files (a.pth, b.pth): keep one there, or choose one with "
        f"--weights or ${ENV_VAR}"
    )


def test_a_wrong_value_is_never_passed_over(tmp_path, user_dir, checkpoint, monkeypatch):
    (user_dir / "good.pth").symlink_to(checkpoint)  # would load, but nobody asked for it
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "typo.pth"))
    with pytest.raises(CheckpointError, match=r"typo.pth does not .*\(weights from \$PAIRVPR_WE"):
        load_model()
    monkeypatch.delenv(ENV_VAR)
    params = _params(tmp_path / "p.yaml", str(tmp_path / "typo2.pth"))
    with pytest.raises(
        CheckpointError, match=rf"typo2.pth does not .*from 'weights' in {params}\)"
    ):
        load_model(params_file=params)
    with pytest.raises(ConfigError, match="cannot read parameter file .*missing.yaml"):
        resolve_weights(None, tmp_path / "missing.yaml")


def test_load_from_each_place(tmp_path, user_dir, checkpoint, monkeypatch):
    fingerprint = load_model(checkpoint).fingerprint
    (user_dir / "only.pth").symlink_to(checkpoint)
    assert load_model().fingerprint == fingerprint
    monkeypatch.setenv(ENV_VAR, str(checkpoint))
    assert load_model(params_file=_params(tmp_path / "p.yaml", "x.pth")).fingerprint == (
        fingerprint
    )
    found = resolve_weights()
    assert load_model(found).fingerprint == fingerprint


def test_missing_and_garbage_checkpoints_name_the_source(tmp_path):
    with pytest.raises(CheckpointError, match=r"missing.pth does not exist.*\(weights from -"):
        load_model(tmp_path / "missing.pth")
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=r"garbage.pth.*\(weights from parameter weights\)"):
        load_model(garbage, explicit_name="parameter weights")


@pytest.mark.parametrize(
    ("device", "precision", "message"),
    [
        ("gpu0", "fp32", "device 'gpu0' is not a torch device"),
        ("cpu", "fp16", "precision fp16 needs a CUDA device"),
        ("meta", "fp32", "only cpu and cuda devices are supported"),
        ("cpu", "fp8", "precision 'fp8' must be one of fp32, int8, bf16, fp16"),
    ],
)
def test_device_and_precision_are_checked(device, precision, message):
    with pytest.raises(ConfigError, match=message):
        load_model("random-tiny", device=device, precision=precision)


@pytest.mark.parametrize(
    "backend, precision, message",
    [
        ("openvno", "fp32", "backend 'openvno' must be one of torch, openvino"),
        ("onnx", "int8", "backend 'onnx' must be one of torch, openvino"),
        ("openvino", "fp16", "precision fp16 needs a CUDA device"),
    ],
)
def test_backend_is_checked(backend, precision, message):
    with pytest.raises(ConfigError, match=message):
        load_model("random-tiny", precision=precision, backend=backend)


@pytest.mark.parametrize("missing", ["openvino", "nncf"])
def test_backend_without_its_package_says_how_to_get_it(monkeypatch, missing):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == missing else find_spec(name)
    )
    message = (
        f"backend openvino needs the package '{missing}', which is not installed: pip install "
        "'pair_vpr_ros[openvino]' (make setup installs it), or use backend torch"
    )
    with pytest.raises(ConfigError) as info:
        load_model("random-tiny", precision="int8", backend="openvino")
    assert str(info.value) == message
    if missing == "nncf":  # fp32 and bf16 need openvino alone
        assert check_runtime("cpu", "fp32", "openvino") == torch.device("cpu")


def test_random_presets_and_int8():
    model = load_model("random-tiny", image_size=28)
    assert model.config.image_size == 28 and model.fingerprint.startswith("random-init:0|tiny")
    assert not model.training and next(model.parameters()).device == torch.device("cpu")
    assert load_model("random-tiny", precision="int8").fingerprint.startswith("random-init:0+int8")
    assert load_model("random-small").config.arch == "small"
    with pytest.raises(ConfigError, match="unknown model preset 'huge'"):
        load_model("random-huge")
