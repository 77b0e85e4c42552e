"""Issue 24's training changes: stage one's decoder table and optimiser, mining without the
lighting shortcut, identical pairs, the held-out measurement and the curves."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from synthetic_data import place_image, write_rgb

from pair_vpr_ros.learn.heldout import HeldoutViews, auc, average_precision, encode_views, measure
from pair_vpr_ros.learn.image_files import read_rgb
from pair_vpr_ros.learn.train.common import DistContext, set_trainable
from pair_vpr_ros.learn.train.curves import GREY_KEYS, draw_curves, heldout_hook, read_records
from pair_vpr_ros.learn.train.data import (
    PlaceBatchSampler,
    choose_views,
    near_identical,
    view_condition,
)
from pair_vpr_ros.learn.train.losses import (
    random_patch_mask,
    relation_hard_indices,
    same_condition_negatives,
)
from pair_vpr_ros.learn.train.stage1 import Stage1, Stage1Config, Stage1Objective
from pair_vpr_ros.learn.train.stage2 import Stage2, Stage2Config, Stage2Objective
from pair_vpr_ros.model import ModelConfig, build_pairvpr, save_pairvpr
from pair_vpr_ros.model.decoder import sincos_table


def _place_views(root: Path, places: int = 4, views: int = 6, size: int = 64) -> Path:
    """ROOT/place_XX/<k>.png: view k is in condition k mod 3, as the demo place datasets."""
    for p in range(places):
        for k in range(views):
            write_rgb(root / f"place_{p:02d}" / f"{k}.png", place_image(p, k, size))
    return root


def test_heldout_grey_is_what_a_mono8_camera_gives(tmp_path) -> None:
    """measure(grey=True) on colour files equals measure on the files made grey beforehand
    (BT.601 luma in all three channels, as `images.convert` turns a mono8 frame into RGB)."""
    root = _place_views(tmp_path / "colour", places=4)
    for path in sorted(root.rglob("*.png")):
        luma = cv2.cvtColor(read_rgb(path), cv2.COLOR_RGB2GRAY)
        write_rgb(tmp_path / "grey" / path.relative_to(root), cv2.merge([luma] * 3))
    model = build_pairvpr(ModelConfig.tiny(), seed=0)
    in_grey = measure(model, HeldoutViews.load(root), k=5, grey=True)
    made_grey = measure(model, HeldoutViews.load(tmp_path / "grey"), k=5)
    assert in_grey == pytest.approx(made_grey, rel=0, abs=0, nan_ok=True)
    paths = HeldoutViews.load(root).paths
    grey_desc, colour_desc = (
        encode_views(model, paths, grey=True)[1],
        encode_views(model, paths)[1],
    )
    assert torch.equal(
        grey_desc, encode_views(model, HeldoutViews.load(tmp_path / "grey").paths)[1]
    )
    assert not torch.allclose(grey_desc, colour_desc, atol=1e-3)


def test_stage_one_decoder_table_is_the_sincos_table_of_the_training_grid(tmp_path) -> None:
    """ViT-B at 224 px: the true 16x16 table, not the 23x23 one shrunk (issue 24, point 0)."""
    cfg = Stage1Config(data=[], out_dir=tmp_path, arch="B", image_size=224)
    model = Stage1(cfg).start_model(DistContext())
    assert model.config.dec_pos_grid == 16
    assert torch.equal(model.dec_pos_embed, sincos_table(16, 768))
    assert torch.equal(model.dec_pos_embed_cls[1:], sincos_table(16, 768))
    assert not model.dec_pos_embed_cls[0].any()
    shrunk = F.interpolate(
        sincos_table(23, 768).reshape(1, 23, 23, -1).permute(0, 3, 1, 2),
        size=(16, 16),
        mode="bicubic",
        align_corners=False,
    )
    shrunk = shrunk.permute(0, 2, 3, 1).reshape(256, -1)
    assert (shrunk - model.dec_pos_embed).abs().max() > 1.0  # what the old code trained with


def test_stage_two_stretches_stage_one_table_to_its_grid(tmp_path) -> None:
    """Stage one at 84 px (6x6 table), stage two at 112 px: 8x8, resized as the network spec
    says, and stored so that the checkpoint holds it (as the released ones hold 23x23)."""
    s1 = Stage1(Stage1Config(data=[], out_dir=tmp_path, arch="tiny", image_size=84))
    first = s1.start_model(DistContext())
    assert torch.equal(first.dec_pos_embed, sincos_table(6, 32))
    path = save_pairvpr(first, tmp_path / "stage1_final.pt", extra={"stage": 1})
    cfg = Stage2Config(data=[], out_dir=tmp_path, arch="tiny", image_size=112, init=path)
    second = Stage2(cfg).start_model(DistContext())
    grid = sincos_table(6, 32).reshape(1, 6, 6, -1).permute(0, 3, 1, 2)
    want = F.interpolate(grid, size=(8, 8), mode="bicubic", align_corners=False)
    want = want.permute(0, 2, 3, 1).reshape(64, -1)
    assert second.config.dec_pos_grid == 8
    assert torch.allclose(second.dec_pos_embed, want, atol=1e-6)
    assert torch.allclose(second.dec_pos_embed_cls[1:], want, atol=1e-6)


def test_stage_one_frozen_blocks_keep_no_autograd_state() -> None:
    model = build_pairvpr(ModelConfig.tiny(with_stage1_head=True), seed=0).train()
    names = set_trainable(model, 1, train_blocks=1)
    assert "encoder.model.mask_token" not in names
    seen = {}
    for i, block in enumerate(model.encoder.model.blocks):
        block.register_forward_hook(lambda m, a, out, i=i: seen.__setitem__(i, out.requires_grad))
    images = torch.randn(2, 3, 56, 56)
    loss = Stage1Objective(model)(images, images.flip(0), random_patch_mask(2, 16, 0.9))
    loss.backward()
    assert seen == {0: False, 1: True}


def test_stage_one_schedule_follows_the_authors(tmp_path) -> None:
    cfg = Stage1Config(data=[], out_dir=tmp_path, arch="tiny", lr=1e-3, warmup_steps=10)
    stage = Stage1(cfg)
    assert stage.lr_factor(9, 200) == pytest.approx(1.0)
    assert stage.lr_factor(200, 200) * 1e-3 == pytest.approx(1e-6)
    assert stage.weight_decay_at(0, 200) == pytest.approx(0.04)
    assert stage.weight_decay_at(100, 200) == pytest.approx(0.22)
    assert stage.weight_decay_at(200, 200) == pytest.approx(0.4)
    opt = stage.optimizer(build_pairvpr(ModelConfig.tiny(with_stage1_head=True), seed=0))
    assert opt.defaults["betas"] == (0.9, 0.999)


def test_views_pair_up_by_condition_and_the_epoch_travels_in_the_index() -> None:
    assert [view_condition(Path(f"{k}.png"), 3) for k in (0, 4, 5)] == [0, 1, 2]
    assert view_condition(Path("img_1.png"), 3) == -1 and view_condition(Path("4.png"), 0) == -1
    rng = np.random.default_rng(0)
    conds = [0, 1, 2, 0, 1, 2]
    for _ in range(20):
        chosen = choose_views(conds, 4, rng, pair_conditions=True)
        got = [conds[i] for i in chosen]
        assert len(set(chosen)) == 4 and got[0] == got[1] and got[2] == got[3] != got[0]
    assert len(choose_views([0, 1, 2, 0], 4, rng, pair_conditions=True)) == 4  # falls back
    sampler = PlaceBatchSampler(8, 4, seed=0)
    sampler.set_epoch(3)
    assert all(e == 3 for batch in sampler for e, _ in batch)


def test_relation_mining_gives_positive_and_negative_the_same_lighting_relation() -> None:
    # 2 places x 4 views; conditions 0,0,1,1 in each place; descriptors make the shortcut
    # mining pick a cross-lighting positive and a same-lighting negative for every anchor.
    labels = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1])
    conds = torch.tensor([0, 0, 1, 1, 0, 0, 1, 1])
    sim = torch.where(conds[:, None] == conds[None, :], 0.9, 0.1) + 0.01 * torch.randn(8, 8)
    own = torch.arange(8)
    pos, neg, valid = relation_hard_indices(sim, labels, labels, own, conds, conds)
    assert valid.all()
    assert (labels[pos] == labels).all() and (labels[neg] != labels).all() and (pos != own).all()
    same_pos, same_neg = conds[pos] == conds, conds[neg] == conds
    assert torch.equal(same_pos, same_neg)  # no lighting shortcut
    assert same_pos.tolist() == [True, False] * 4  # both relations in equal shares
    for _ in range(5):  # random negatives: another place, still the anchor's relation
        pos, neg, valid = relation_hard_indices(sim, labels, labels, own, conds, conds, True)
        assert valid.all() and (labels[neg] != labels).all()
        assert torch.equal(conds[pos] == conds, conds[neg] == conds)


def test_identical_pairs_are_balanced_by_same_lighting_negatives() -> None:
    labels = torch.tensor([0, 0, 1, 1, 2, 2])
    conds = torch.tensor([0, 1, 0, 1, 1, 1])
    for _ in range(5):
        neg = same_condition_negatives(labels[:2], labels, conds[:2], conds)
        assert neg[0].item() == 2 and neg[1].item() in (3, 4, 5)
    assert same_condition_negatives(labels[:1], labels, torch.tensor([7]), conds)[0] >= 2
    assert (labels[same_condition_negatives(labels, labels, None, None)] != labels).all()


def test_identical_and_near_identical_pairs_train_as_positives(tmp_path) -> None:
    torch.manual_seed(0)
    ramp = torch.linspace(-2.0, 2.0, 56)
    images = (ramp[None, :] + ramp[:, None]).expand(3, 3, 56, 56) / 2  # smooth, as photos
    twins = near_identical(images)
    assert twins.shape == images.shape
    assert 0.01 < (twins - images).abs().mean() < 0.2  # moved and noised, but barely
    model = build_pairvpr(ModelConfig.tiny(), seed=0).train()
    set_trainable(model, 2, train_blocks=2)
    labels = torch.arange(4).repeat_interleave(4)
    conds = torch.tensor([0, 0, 1, 1] * 4)
    cfg = Stage2Config(data=[], out_dir=tmp_path, twin_share=0.25, conditions=3)
    terms = Stage2Objective(model, cfg, DistContext())(torch.randn(16, 3, 56, 56), labels, conds)
    assert terms["pair"] > 0 and 0.0 <= terms["pair_rank"] <= 1.0
    terms["loss"].backward()
    assert model.classvprmodule[2].weight.grad.abs().sum() > 0


def test_average_precision_and_auc_known_answers() -> None:
    ap, r90 = average_precision(np.array([0.9, 0.8, 0.7, 0.6]), np.array([1, 0, 1, 1], bool))
    assert ap == pytest.approx((1 + 2 / 3 + 3 / 4) / 4) and r90 == pytest.approx(0.25)
    assert auc(np.array([3.0, 2.0, 1.0]), np.array([True, False, False])) == 1.0
    assert auc(np.array([1.0, 1.0]), np.array([True, False])) == 0.5
    assert np.isnan(auc(np.array([1.0]), np.array([True])))


def test_heldout_measure_and_curves(tmp_path) -> None:
    root = _place_views(tmp_path / "held", places=4)
    views = HeldoutViews.load(root)
    assert len(views.paths) == 24 and len(views.queries) == 8
    assert views.conds.tolist()[:6] == [0, 1, 2, 0, 1, 2]
    model = build_pairvpr(ModelConfig.tiny(), seed=0)
    got = measure(model, views, k=5)
    assert set(got) >= {"global_ap", "rerank_ap", "lighting_auc", "identical_ge_revisit"}
    assert all(0.0 <= got[k] <= 1.0 for k in ("global_ap", "rerank_ap", "global_r@1"))
    out = tmp_path / "run"
    out.mkdir()
    every, run = heldout_hook(model, root, 5, out, k=5)
    hooked = run(5)
    assert every == 5 and hooked["global_ap"] == pytest.approx(got["global_ap"])
    grey = measure(model, views, k=5, grey=True)
    assert {k: hooked[f"grey_{k}"] for k in GREY_KEYS} == {k: grey[k] for k in GREY_KEYS}
    (out / "train_log.jsonl").write_text(
        '{"step": 1, "loss": 2.0, "pair": 0.7}\n{"step": 5, "heldout": {"global_ap": 0.5}}\n'
    )
    png = draw_curves([("s2", out / "train_log.jsonl")], out / "curves.png")
    assert png.read_bytes()[:4] == b"\x89PNG"
    (out / "tune.jsonl").write_text(  # the drive stage's validation records
        '{"step": 1, "loss": 0.6}\n{"step": 0, "val": {"global": 0.8, "rerank_10": 0.85}}\n'
    )
    steps, evals = read_records(out / "tune.jsonl")
    assert ([r["step"] for r in steps], [r["step"] for r in evals]) == ([1], [0])
    draw_curves([("s2", out / "train_log.jsonl"), ("tune", out / "tune.jsonl")], png)
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert heldout_hook(model, None, 5, out) is None and heldout_hook(model, root, 0, out) is None
