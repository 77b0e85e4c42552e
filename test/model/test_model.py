"""The network: parameter names/shapes of the released models, fast path == reference path."""

from __future__ import annotations

import math

import pytest
import torch

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.model import ModelConfig, PairVPR, PairVPRModel, build_pairvpr, quantize_int8
from pair_vpr_ros.model.decoder import sincos_table

SIZES = {
    "S": (384, 12, False),
    "B": (768, 12, False),
    "L": (1024, 24, False),
    "G": (1536, 40, True),
}


@pytest.fixture(scope="module")
def meta_models():
    with torch.device("meta"):
        return {a: PairVPR(ModelConfig.preset(a)) for a in SIZES}


@pytest.mark.parametrize("arch", list(SIZES))
def test_released_parameter_names_and_shapes(meta_models, arch):
    d, depth, swiglu = SIZES[arch]
    shapes = {k: tuple(v.shape) for k, v in meta_models[arch].state_dict().items()}
    enc = "encoder.model."
    expected = {
        enc + "cls_token": (1, 1, d),
        enc + "register_tokens": (1, 4, d),
        enc + "mask_token": (1, d),
        enc + "pos_embed": (1, 1 + 37 * 37, d),
        enc + "patch_embed.proj.weight": (d, 3, 14, 14),
        enc + f"blocks.{depth - 1}.attn.qkv.weight": (3 * d, d),
        enc + f"blocks.{depth - 1}.ls2.gamma": (d,),
        enc + "norm.weight": (d,),
        "globalizer.0.weight": (512, d),
        "decoder_embed.weight": (768, d),
        "decoder_clstoken": (1, 1, 768),
        "dec_pos_embed": (529, 768),
        "dec_pos_embed_cls": (530, 768),
        "dec_blocks.11.cross_attn.projq.weight": (768, 768),
        "dec_blocks.11.cross_attn.projk.bias": (768,),
        "dec_blocks.11.norm_y.weight": (768,),
        "dec_blocks.11.mlp.fc1.weight": (3072, 768),
        "dec_norm.bias": (768,),
        "classvprmodule.0.weight": (512, 768),
        "classvprmodule.2.weight": (1, 512),
    }
    if swiglu:
        expected[enc + "blocks.0.mlp.w12.weight"] = (8192, d)
        expected[enc + "blocks.0.mlp.w3.weight"] = (d, 4096)
    else:
        expected[enc + "blocks.0.mlp.fc1.weight"] = (4 * d, d)
        expected[enc + "blocks.0.mlp.fc2.weight"] = (d, 4 * d)
    assert {k: shapes.get(k) for k in expected} == expected
    assert not any(k.startswith(("mask_token", "prediction_head", "decoder.")) for k in shapes)
    assert len([k for k in shapes if k.startswith("dec_blocks.")]) == 12 * 24
    assert sum(1 for k in shapes if k.startswith(enc + "blocks.")) == depth * 14


@pytest.mark.parametrize("arch,millions", [("S", 22.1), ("B", 86.6), ("L", 304.4), ("G", 1136.5)])
def test_encoder_parameter_counts(meta_models, arch, millions):
    count = sum(p.numel() for n, p in meta_models[arch].named_parameters() if n.startswith("enc"))
    assert round(count / 1e6, 1) == millions


@pytest.mark.parametrize("arch", list(SIZES))
def test_config_read_off_shapes(meta_models, arch):
    cfg = ModelConfig.from_state_dict(meta_models[arch].state_dict())
    assert cfg == ModelConfig.preset(arch)


def test_decoder_position_table_values():
    table = sincos_table(23, 768)
    r, c = 5, 7
    row = table[r * 23 + c]
    assert row[0].item() == pytest.approx(math.sin(c))
    assert row[192].item() == pytest.approx(math.cos(c))
    assert row[1].item() == pytest.approx(math.sin(c * 10000 ** (-1 / 192)))
    assert row[384].item() == pytest.approx(math.sin(r))
    assert row[576].item() == pytest.approx(math.cos(r))


@pytest.fixture(scope="module")
def tiny():
    return build_pairvpr(ModelConfig.tiny(), seed=3)


@pytest.mark.parametrize("size", [56, 70])  # 70 px: grids differ from both stored tables
def test_fast_path_equals_reference(tiny, size):
    images = torch.randn(5, 3, size, size, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        dense, desc = tiny.encode(images)
        ref_dense, ref_desc = tiny.encode(images, fast=False)
        assert dense.shape == (5, (size // 14) ** 2, 32) and desc.shape == (5, 512)
        assert torch.allclose(desc.norm(dim=-1), torch.ones(5))
        assert (desc - ref_desc).abs().max() <= 1e-5
        assert (dense - ref_dense).abs().max() <= 1e-5
        fast = tiny.pair_scores(dense[0], dense[1:], chunk=3)
        ref = tiny.pair_scores_reference(dense[0], dense[1:])
    assert fast.shape == (4,)
    assert (fast - ref).abs().max() <= 1e-4


def test_pair_score_is_sum_of_both_directions(tiny):
    dense, _ = tiny.encode(torch.randn(2, 3, 56, 56))
    with torch.no_grad():
        forward = tiny.pair_logits(dense[:1], dense[1:])
        backward = tiny.pair_logits(dense[1:], dense[:1])
        score = tiny.pair_scores(dense[0], dense[1:])
    assert torch.allclose(score, forward + backward, atol=1e-5)
    assert tiny.pair_scores(dense[0], dense[:0]).shape == (0,)


def test_one_direction_at_a_time_is_the_same_arithmetic(tiny):
    """The re-rank cascade's `QueryScorer.logits`: each direction as the plain path computes
    it, and their sum the fast path's score (to float rounding: other batch sizes)."""
    dense, _ = tiny.encode(torch.randn(6, 3, 56, 56, generator=torch.Generator().manual_seed(1)))
    q, cands = dense[0], dense[1:]
    with torch.no_grad():
        scorer = tiny.query_scorer(q, chunk=2)
        qc, cq = scorer.logits(cands, "query"), scorer.logits(cands, "candidate")
        first = q[None].expand(5, -1, -1)
        torch.testing.assert_close(qc, tiny.pair_logits(first, cands, fast=False), atol=1e-5,
                                   rtol=0)  # fmt: skip
        torch.testing.assert_close(cq, tiny.pair_logits(cands, first, fast=False), atol=1e-5,
                                   rtol=0)  # fmt: skip
        torch.testing.assert_close(qc + cq, tiny.pair_scores(q, cands, chunk=2), atol=1e-6,
                                   rtol=0)  # fmt: skip
        assert torch.equal(scorer.scores(cands), tiny.pair_scores(q, cands, chunk=2))
        assert scorer.logits(cands[:0], "query").shape == (0,)
    with pytest.raises(ValueError, match="first must be one of .*got 'both'"):
        scorer.logits(cands, "both")


def test_single_block_decoder_fast_path():
    model = build_pairvpr(ModelConfig.tiny(dec_depth=1), seed=1)
    with torch.no_grad():
        dense, _ = model.encode(torch.randn(3, 3, 56, 56))
        assert torch.allclose(
            model.pair_scores(dense[0], dense),
            model.pair_scores_reference(dense[0], dense),
            atol=1e-5,
        )


def test_image_size_must_be_multiple_of_patch(tiny):
    with pytest.raises(ConfigError, match="image_size=100 is not a positive multiple of 14"):
        ModelConfig.tiny(image_size=100)
    with pytest.raises(ConfigError, match="image size 50x56 is not a multiple of 14 pixels"):
        tiny.encode(torch.zeros(1, 3, 50, 56))


def test_int8_keeps_outputs_close_and_leaves_original(tiny):
    q = quantize_int8(tiny)
    assert tiny.encoder.model.blocks[0].attn.qkv.__class__ is torch.nn.Linear
    images = torch.randn(3, 3, 56, 56)
    with torch.no_grad():
        _, desc = tiny.encode(images)
        _, qdesc = q.encode(images)
    assert (desc * qdesc).sum(-1).min() > 0.99
    assert q.fingerprint != tiny.fingerprint and "+int8" in q.fingerprint


def test_model_built_inside_inference_mode_encodes():
    with torch.inference_mode():
        model = build_pairvpr(ModelConfig.tiny(), seed=0)
        dense, desc = model.encode(torch.randn(1, 3, 70, 70))
        scores = model.pair_scores(dense[0], dense)
    assert desc.shape == (1, 512) and scores.shape == (1,)


def test_dense_dtype_follows_the_decoder(tiny):
    assert isinstance(tiny, PairVPRModel)
    assert tiny.dense_dtype == torch.float32 and quantize_int8(tiny).dense_dtype == torch.float32
    assert (
        build_pairvpr(ModelConfig.tiny(), seed=0).to(torch.bfloat16).dense_dtype == torch.bfloat16
    )
