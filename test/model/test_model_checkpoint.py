"""Loading weights: released layouts, our format, DINOv2 backbones, and every bad file."""

from __future__ import annotations

import re

import pytest
import torch

from pair_vpr_ros.errors import CheckpointError
from pair_vpr_ros.model import (
    ModelConfig,
    build_pairvpr,
    load_dinov2_encoder,
    load_pairvpr,
    save_encoder_backbone,
    save_pairvpr,
)
from pair_vpr_ros.model.checkpoint import STAGE2_NEW

# 64-d heads as in the released models, so the config can be read off the shapes.
RELEASED_LIKE = ModelConfig(
    arch="custom-128",
    embed_dim=128,
    depth=2,
    num_heads=2,
    mlp_hidden=512,
    pos_grid=4,
    dec_dim=128,
    dec_depth=2,
    dec_heads=2,
    dec_mlp_hidden=256,
    dec_pos_grid=4,
    cls_hidden=32,
    image_size=56,
)


@pytest.fixture(scope="module")
def model():
    return build_pairvpr(RELEASED_LIKE, seed=0)


@pytest.fixture(scope="module")
def images():
    return torch.randn(2, 3, 56, 56, generator=torch.Generator().manual_seed(1))


def outputs(net, images):
    with torch.no_grad():
        dense, desc = net.encode(images)
        return dense, desc, net.pair_scores(dense[0], dense)


def assert_same(a, b):
    for x, y in zip(a, b, strict=True):
        assert torch.equal(x, y)


@pytest.mark.parametrize(
    "wrap",
    [
        lambda sd: sd,
        lambda sd: {"model": sd, "epoch": 3},
        lambda sd: {"model": {"model": {f"module.{k}": v for k, v in sd.items()}}},
    ],
    ids=["plain", "model-wrapper", "nested-ddp"],
)
def test_released_layouts_load_unchanged(tmp_path, model, images, wrap):
    path = tmp_path / "w.pth"
    torch.save(wrap(model.state_dict()), path)
    loaded = load_pairvpr(path, image_size=56)
    assert loaded.config == RELEASED_LIKE
    assert_same(outputs(loaded, images), outputs(model, images))
    assert loaded.weights_id.startswith("sha256:")


def test_our_format_round_trip_keeps_non_default_heads(tmp_path, images):
    tiny = build_pairvpr(ModelConfig.tiny(), seed=2)  # 16-d heads: only the stored arch knows
    loaded = load_pairvpr(save_pairvpr(tiny, tmp_path / "sub" / "t.pth"))
    assert loaded.config == tiny.config
    assert_same(outputs(loaded, images), outputs(tiny, images))
    assert list(tmp_path.joinpath("sub").iterdir()) == [tmp_path / "sub" / "t.pth"]


def test_fingerprint_tracks_weights_and_input_size(tmp_path, model):
    path = tmp_path / "w.pth"
    torch.save(model.state_dict(), path)
    a, b = load_pairvpr(path, image_size=56), load_pairvpr(path, image_size=70)
    assert a.fingerprint != b.fingerprint and a.weights_id == b.weights_id
    torch.save(build_pairvpr(RELEASED_LIKE, seed=5).state_dict(), path)
    assert load_pairvpr(path, image_size=56).weights_id != a.weights_id


def test_stage_one_checkpoint_starts_stage_two(tmp_path, model):
    stage1 = build_pairvpr(ModelConfig(**{**RELEASED_LIKE.to_dict(), "with_stage1_head": True}))
    sd = {k: v for k, v in stage1.state_dict().items() if not k.startswith(STAGE2_NEW)}
    path = tmp_path / "stage1.pth"
    torch.save({"model": sd}, path)
    with pytest.raises(CheckpointError, match=r"missing keys \(e.g. \['decoder_clstoken'"):
        load_pairvpr(path, image_size=56)
    loaded = load_pairvpr(path, image_size=56, allow_missing=STAGE2_NEW)
    assert torch.equal(loaded.dec_blocks[0].mlp.fc1.weight, stage1.dec_blocks[0].mlp.fc1.weight)
    assert not hasattr(loaded, "prediction_head")


def test_dinov2_backbone_loads_into_encoder(tmp_path, model):
    path = tmp_path / "dinov2_vits14_reg4_pretrain.pth"
    torch.save(model.encoder.model.state_dict(), path)
    fresh = build_pairvpr(RELEASED_LIKE, seed=9)
    assert load_dinov2_encoder(fresh, path) == []
    assert torch.equal(fresh.encoder.model.pos_embed, model.encoder.model.pos_embed)
    with pytest.raises(CheckpointError, match="looks like a DINOv2 backbone"):
        load_pairvpr(path)
    other = build_pairvpr(ModelConfig.tiny())
    with pytest.raises(
        CheckpointError, match=r"are D=128 with 2 blocks, but the model's encoder is D=32"
    ):
        load_dinov2_encoder(other, path)


def test_our_encoder_saved_as_a_backbone_loads_like_dinov2(tmp_path, model):
    path = save_encoder_backbone(model, tmp_path / "enc" / "encoder_reg4.pth")
    fresh = build_pairvpr(RELEASED_LIKE, seed=9)
    assert load_dinov2_encoder(fresh, path) == []
    for name, tensor in model.encoder.model.state_dict().items():
        assert torch.equal(fresh.encoder.model.state_dict()[name], tensor), name
    assert not torch.equal(fresh.globalizer[0].weight, model.globalizer[0].weight)
    assert [p.name for p in path.parent.iterdir()] == ["encoder_reg4.pth"]  # no temp file left


def write_bad(tmp_path, kind, model):
    path = tmp_path / f"{kind}.pth"
    sd = model.state_dict()
    if kind == "truncated":
        torch.save(sd, path)
        path.write_bytes(path.read_bytes()[:5000])
    elif kind == "text":
        path.write_text("<html>404 not found</html>")
    elif kind == "foreign":
        torch.save({"conv1.weight": torch.zeros(4, 3, 7, 7), "fc.bias": torch.zeros(4)}, path)
    elif kind == "list":
        torch.save([torch.zeros(1)], path)
    elif kind == "wrong-shape":
        torch.save({**sd, "dec_blocks.1.mlp.fc1.weight": torch.zeros(7, 128)}, path)
    elif kind == "missing-key":
        torch.save({k: v for k, v in sd.items() if "dec_blocks.1.norm_y" not in k}, path)
    elif kind == "extra-key":
        torch.save({**sd, "head.weight": torch.zeros(2)}, path)
    return path


@pytest.mark.parametrize(
    "kind,message",
    [
        ("missing", "does not exist (or is not a file): pass the path of a Pair-VPR weights file"),
        ("truncated", "could not be read as a PyTorch weights file"),
        ("text", "could not be read as a PyTorch weights file"),
        ("foreign", "is not a Pair-VPR checkpoint: expected key 'encoder.model.cls_token'"),
        ("list", "holds a list, not a state_dict of tensors"),
        (
            "wrong-shape",
            "1 shape mismatches (e.g. ['dec_blocks.1.mlp.fc1.weight: expected (256, 128), "
            "found (7, 128)'])",
        ),
        (
            "missing-key",
            "2 missing keys (e.g. ['dec_blocks.1.norm_y.weight', 'dec_blocks.1.norm_y.bias'])",
        ),
        ("extra-key", "1 unexpected keys (e.g. ['head.weight'])"),
    ],
)
def test_bad_checkpoints_name_file_and_problem(tmp_path, model, kind, message):
    path = tmp_path / "missing.pth" if kind == "missing" else write_bad(tmp_path, kind, model)
    with pytest.raises(CheckpointError, match=re.escape(message)) as info:
        load_pairvpr(path, image_size=56)
    assert str(path) in str(info.value)


def test_config_alone_builds_random_model():
    net = load_pairvpr(None, config=ModelConfig.tiny())
    assert net.config == ModelConfig.tiny() and not net.training
    with pytest.raises(CheckpointError, match="needs a checkpoint path or a ModelConfig"):
        load_pairvpr(None)
