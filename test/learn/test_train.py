"""Training: losses, schedules, freezing, samplers, both trainers, checkpoints, 2-process DDP."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic_data import make_place_folders, make_utm_eval_set

from pair_vpr_ros.errors import ConfigError, DatasetError, TrainingError
from pair_vpr_ros.learn.places import load_place_folders
from pair_vpr_ros.learn.train import driver, stage1, stage2
from pair_vpr_ros.learn.train.common import (
    DistContext,
    apply_weight_decay,
    cosine,
    linear_decay,
    param_groups,
    read_training_state,
    save_training_checkpoint,
    set_trainable,
    warmup_cosine,
)
from pair_vpr_ros.learn.train.data import (
    AugmentConfig,
    PlaceBatchSampler,
    PlaceData,
    PlaceImagesDataset,
    augment_rgb,
    grey_rgb,
    make_loader,
)
from pair_vpr_ros.learn.train.loop import LoopJob, LoopSettings, Progress, run_loop
from pair_vpr_ros.learn.train.losses import (
    MultiSimilarityObjective,
    batch_hard_indices,
    masked_patch_mse,
    patchify,
    random_patch_mask,
    random_positive_indices,
)
from pair_vpr_ros.learn.train.options import config_from_args
from pair_vpr_ros.learn.train.stage1 import Stage1, Stage1Config, Stage1Objective, train_stage1
from pair_vpr_ros.learn.train.stage2 import Stage2Config, Stage2Objective, train_stage2
from pair_vpr_ros.model import ModelConfig, build_pairvpr, load_pairvpr
from pair_vpr_ros.model.preprocess import MEAN, STD

TINY = dict(arch="tiny", image_size=56, workers=0, device="cpu", log_every=1, save_every=0)


def test_patchify_layout() -> None:
    images = torch.arange(3 * 28 * 28, dtype=torch.float32).reshape(1, 3, 28, 28)
    patches = patchify(images)
    assert patches.shape == (1, 4, 588)
    assert patches[0, 1, :3].tolist() == images[0, :, 0, 14].tolist()  # row 0, col 1, pixel 0
    assert patches[0, 2, 3:6].tolist() == images[0, :, 14, 1].tolist()  # row 1, col 0, pixel 1


def test_random_patch_mask_masks_exactly_the_ratio_per_image() -> None:
    mask = random_patch_mask(4, 16, 0.9, torch.Generator().manual_seed(0))
    assert mask.sum(dim=1).tolist() == [14, 14, 14, 14]
    assert len({tuple(row.tolist()) for row in mask}) == 4
    with pytest.raises(ConfigError, match=r"mask ratio 1.0 must be in \(0, 1\)"):
        random_patch_mask(1, 16, 1.0)


def test_masked_patch_mse_uses_only_masked_patches_and_normalised_targets() -> None:
    images = torch.randn(2, 3, 28, 28)
    target = patchify(images)
    target = (target - target.mean(-1, keepdim=True)) / (
        target.var(-1, keepdim=True) + 1e-6
    ).sqrt()
    mask = torch.tensor([[True, False, False, True], [False, False, True, False]])
    pred = torch.where(mask[..., None], target, torch.full_like(target, 50.0))
    assert masked_patch_mse(pred, images, mask).item() == pytest.approx(0.0, abs=1e-10)
    zero = masked_patch_mse(torch.zeros_like(target), images, mask).item()
    assert zero == pytest.approx(587 / 588, rel=1e-4)  # unbiased variance over 588 values


def test_batch_hard_indices_hand_made() -> None:
    sim = torch.tensor([[1.0, 0.8, 0.3, 0.9, 0.1], [0.8, 1.0, 0.6, 0.2, 0.7]])
    labels = torch.tensor([0, 0, 0, 1, 2])
    pos, neg, valid = batch_hard_indices(sim, labels[:2], labels, torch.tensor([0, 1]))
    assert pos.tolist() == [2, 2] and neg.tolist() == [3, 4] and valid.tolist() == [True, True]
    pos, neg, valid = batch_hard_indices(sim[:1], labels[3:4], labels, torch.tensor([3]))
    assert valid.tolist() == [False]


def test_random_positive_indices_pick_another_view_of_the_place() -> None:
    labels = torch.tensor([0, 0, 0, 1, 1, 2])
    own = torch.tensor([0, 3, 5])
    picks = {
        tuple(
            random_positive_indices(labels[own], labels, own, torch.Generator().manual_seed(s))[
                :2
            ].tolist()
        )
        for s in range(40)
    }
    assert {p[0] for p in picks} == {1, 2} and {p[1] for p in picks} == {4}


def test_grey_and_exposure_augmentation() -> None:
    rgb = np.zeros((4, 6, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 100, 50
    assert grey_rgb(rgb)[0, 0].tolist() == pytest.approx([124.2] * 3, abs=1e-3)  # BT.601
    flat = AugmentConfig(crop_scale=(1.0, 1.0), brightness=0.0, contrast=0.0)
    rng = np.random.default_rng(0)
    grey = augment_rgb(rgb, rng, replace(flat, grey=1.0))
    assert grey.shape == (4, 6, 3) and (grey == 124).all()
    assert (augment_rgb(rgb, rng, replace(flat, grey=0.0)) == rgb).all()
    gains = [augment_rgb(rgb, rng, replace(flat, exposure=1.0))[0, 0, 2] / 50 for _ in range(50)]
    assert 0.5 - 1e-6 <= min(gains) < 0.7 and 1.4 < max(gains) <= 2.0 + 1e-6


def test_multi_similarity_objective_and_missing_package(monkeypatch) -> None:  # noqa: ANN001
    torch.manual_seed(0)
    desc = torch.nn.functional.normalize(torch.randn(8, 16), dim=1)
    labels = torch.tensor([0, 0, 1, 1, 2, 2, 3, 3])
    loss, mined = MultiSimilarityObjective()(desc, labels)
    assert loss.item() > 0 and mined > 0
    monkeypatch.setitem(sys.modules, "pytorch_metric_learning", None)
    with pytest.raises(ConfigError, match=r"pip install 'pair_vpr_ros\[train\]'"):
        MultiSimilarityObjective()


def test_schedules() -> None:
    assert [round(warmup_cosine(s, 110, 10), 6) for s in (0, 9, 10, 60, 110)] == [
        0.1,
        1.0,
        1.0,
        0.5,
        0.0,
    ]
    assert warmup_cosine(110, 110, 10, min_factor=0.1) == pytest.approx(0.1)
    assert [linear_decay(s, 100, 0.2) for s in (0, 50, 100, 150)] == pytest.approx(
        [1.0, 0.6, 0.2, 0.2]
    )
    assert [linear_decay(s, 110, 0.2, warmup=10) for s in (0, 9, 10, 60, 110)] == pytest.approx(
        [0.1, 1.0, 1.0, 0.6, 0.2]
    )


def test_set_trainable_and_layer_decay_groups() -> None:
    model = build_pairvpr(ModelConfig.tiny(with_stage1_head=True), seed=0)
    names = set(set_trainable(model, 1, train_blocks=1))
    assert "encoder.model.blocks.1.attn.qkv.weight" in names
    assert {
        "encoder.model.norm.weight",
        "prediction_head.weight",
        "dec_blocks.0.cross_attn.projq.weight",
        "decoder_embed.weight",
    } <= names
    frozen = {
        "encoder.model.mask_token",  # fixed, as the authors train stage one
        "encoder.model.blocks.0.attn.qkv.weight",
        "globalizer.0.weight",
        "mask_token",
        "decoder_clstoken",
        "classvprmodule.0.weight",
        "encoder.model.pos_embed",
    }
    assert not frozen & names
    names2 = set(set_trainable(model, 2, train_blocks=2))
    assert {
        "decoder_clstoken",
        "globalizer.0.weight",
        "classvprmodule.2.bias",
        "encoder.model.pos_embed",
        "encoder.model.blocks.0.mlp.fc1.weight",
    } <= names2
    assert not {"prediction_head.weight", "encoder.model.mask_token", "mask_token"} & names2
    scales = {}
    for group in param_groups(model, 0.05, layer_decay=0.5):
        for p in group["params"]:
            scales[next(n for n, q in model.named_parameters() if q is p)] = (
                group["lr_scale"],
                group["weight_decay"],
            )
    assert scales["encoder.model.pos_embed"] == (0.125, 0.0)
    assert scales["encoder.model.blocks.0.attn.qkv.weight"] == (0.25, 0.05)
    assert scales["encoder.model.blocks.1.attn.qkv.bias"] == (0.5, 0.0)
    assert scales["dec_blocks.0.mlp.fc1.weight"] == (1.0, 0.05)
    # stage one: encoder (2 blocks) and decoder (2 blocks) count together, L = 4
    set_trainable(model, 1, train_blocks=2)
    groups = param_groups(model, 0.04, layer_decay=0.5, with_decoder=True)
    scales = {}
    for group in groups:
        for p in group["params"]:
            scales[next(n for n, q in model.named_parameters() if q is p)] = (
                group["lr_scale"],
                group["weight_decay"],
                group["wd_scale"],
            )
    assert scales["encoder.model.pos_embed"] == (0.5**5, 0.0, 0.0)
    assert scales["encoder.model.blocks.0.attn.qkv.weight"] == (0.5**4, 0.04, 1.0)
    assert scales["encoder.model.blocks.1.attn.qkv.weight"] == (0.5**3, 0.04, 1.0)
    assert scales["decoder_embed.weight"] == (0.5**2, 0.04, 1.0)
    assert scales["dec_blocks.0.mlp.fc1.weight"] == (0.5**2, 0.04, 1.0)
    assert scales["dec_blocks.1.mlp.fc1.weight"] == (0.5, 0.04, 1.0)
    assert scales["prediction_head.weight"] == (1.0, 0.04, 1.0)
    assert scales["dec_norm.weight"] == (1.0, 0.0, 0.0)
    opt = torch.optim.AdamW(groups, lr=1.0)
    apply_weight_decay(opt, 0.4)
    assert sorted({g["weight_decay"] for g in opt.param_groups}) == [0.0, 0.4]
    assert [cosine(s, 10, 0.04, 0.4) for s in (0, 5, 10, 20)] == pytest.approx(
        [0.04, 0.22, 0.4, 0.4]
    )
    global_only = set(set_trainable(model, 2, train_blocks=2, decoder=False))
    assert global_only == {n for n in names2 if n.startswith(("encoder.", "globalizer."))}
    with pytest.raises(ConfigError, match=r"train_blocks=3 must be in 1..2"):
        set_trainable(model, 2, train_blocks=3)


def test_place_batch_sampler_partitions_places_across_ranks() -> None:
    ranks = [PlaceBatchSampler(23, 3, rank=r, world_size=2, seed=1) for r in range(2)]
    batches = [list(s) for s in ranks]
    assert [len(b) for b in batches] == [3, 3] and all(len(x) == 3 for b in batches for x in b)
    seen = [p for b in batches for x in b for p in x]
    assert len(seen) == len(set(seen)) == 18
    ranks[0].set_epoch(1)
    assert list(ranks[0]) != batches[0]
    ranks[0].set_epoch(0, start_batch=2)
    assert list(ranks[0]) == batches[0][2:]
    with pytest.raises(DatasetError, match=r"5 places cannot fill one batch of 3 places on each"):
        PlaceBatchSampler(5, 3, rank=0, world_size=2)


def test_place_images_dataset(tmp_path: Path) -> None:
    make_place_folders(tmp_path, places=3, per_place=3)
    (tmp_path / "place_01" / "img_2.png").unlink()
    data = PlaceImagesDataset(load_place_folders(tmp_path), 3, size=28, seed=0)
    assert len(data) == 2 and data.dropped_places == 1 and data.labels == [0, 2]
    images, labels, conds = data[1]
    assert images.shape == (3, 3, 28, 28) and labels.tolist() == [2, 2, 2]
    assert conds.tolist() == [-1, -1, -1]  # img_<k>.png names carry no condition
    assert torch.equal(data[(0, 1)][0], images)  # (epoch, place) indices: persistent workers
    assert torch.equal(data[1][0], images)  # same epoch, same draw
    data.set_epoch(1)
    assert not torch.equal(data[1][0], images)  # new epoch, new order of the 3 images


def _is_grey(images: torch.Tensor) -> list[bool]:
    """[k,3,S,S] normalised -> per image: are its three channels one grey value?"""
    mean, std = torch.tensor(MEAN).view(3, 1, 1), torch.tensor(STD).view(3, 1, 1)
    pixels = images * std + mean
    return [bool((p.amax(0) - p.amin(0)).max() < 1e-5) for p in pixels]


def test_grey_places_turn_whole_places_grey(tmp_path: Path) -> None:
    make_place_folders(tmp_path, places=12, per_place=3)
    places = load_place_folders(tmp_path)
    colour = PlaceImagesDataset(places, 3, size=28, seed=0)
    assert not any(g for i in range(12) for g in _is_grey(colour[i][0]))
    grey = PlaceImagesDataset(places, 3, size=28, seed=0, grey_places=1.0)
    assert all(g for i in range(12) for g in _is_grey(grey[i][0]))
    # 0 draws nothing: the same images as a dataset without the option
    off = PlaceImagesDataset(places, 3, size=28, seed=0, grey_places=0.0)
    assert all(torch.equal(off[i][0], colour[i][0]) for i in range(12))
    half = PlaceImagesDataset(places, 3, size=28, seed=0, grey_places=0.5)
    kinds = [set(_is_grey(half[i][0])) for i in range(12)]
    assert all(len(k) == 1 for k in kinds)  # a place is all grey or all colour
    assert {next(iter(k)) for k in kinds} == {True, False}


def _batch(tmp_path: Path, places: int, per_place: int) -> tuple[torch.Tensor, torch.Tensor]:
    make_place_folders(tmp_path, places=places, per_place=per_place)
    data = PlaceImagesDataset(load_place_folders(tmp_path), per_place, size=56)
    items = [data[i] for i in range(places)]
    return torch.stack([i[0] for i in items]), torch.stack([i[1] for i in items])


def _fit(objective: torch.nn.Module, loss_of, steps: int = 8) -> list[float]:  # noqa: ANN001
    params = [p for p in objective.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=2e-3)
    losses = []
    for _ in range(steps):
        loss = loss_of()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    return losses


@pytest.mark.slow
def test_stage_objectives_reduce_their_loss_on_a_fixed_batch(tmp_path: Path) -> None:
    torch.manual_seed(0)
    images, labels = _batch(tmp_path, places=3, per_place=2)
    model = build_pairvpr(ModelConfig.tiny(with_stage1_head=True), seed=0).train()
    set_trainable(model, 1, 2)
    mask = random_patch_mask(3, model.num_patches, 0.9, torch.Generator().manual_seed(0))
    obj1 = Stage1Objective(model)
    losses = _fit(obj1, lambda: obj1(images[:, 0], images[:, 1], mask))
    assert losses[-1] < 0.9 * losses[0]
    set_trainable(model, 2, 2)
    obj2 = Stage2Objective(model, Stage2Config(data=[], out_dir=tmp_path), DistContext())
    losses = _fit(obj2, lambda: obj2(images.flatten(0, 1), labels.flatten())["loss"])
    assert losses[-1] < 0.9 * losses[0]


def test_stage_two_patch_loss_and_random_positives(tmp_path: Path) -> None:
    images, labels = _batch(tmp_path, places=3, per_place=2)
    images, labels = images.flatten(0, 1), labels.flatten()
    model = build_pairvpr(ModelConfig.tiny(), seed=0)
    terms = {}
    for weight, positives in ((0.0, "hardest"), (0.5, "hardest"), (0.5, "random")):
        cfg = Stage2Config(
            data=[], out_dir=tmp_path, patch_weight=weight, pair_positives=positives
        )
        torch.manual_seed(0)
        terms[weight, positives] = Stage2Objective(model, cfg, DistContext())(images, labels)
    off, on = terms[0.0, "hardest"], terms[0.5, "hardest"]
    assert off["patch"].item() == 0.0 and on["patch"].item() > 0.0
    assert on["loss"].item() == pytest.approx(off["loss"].item() + 0.5 * on["patch"].item())
    # two views per place: the only other view is both the hardest and a random positive
    assert terms[0.5, "random"]["pair"].item() == pytest.approx(on["pair"].item(), rel=1e-6)


def test_stage_two_global_only_leaves_the_decoder_alone(trained: dict[str, Path]) -> None:
    out = trained["root"] / "s2_global"
    final = train_stage2(
        Stage2Config(
            data=[str(trained["data"])],
            out_dir=out,
            init=trained["s2"],
            epochs=1,
            places_per_batch=3,
            pair_weight=0.0,
            warmup_steps=2,
            **TINY,
        )
    )
    before, after = load_pairvpr(trained["s2"]).state_dict(), load_pairvpr(final).state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith(("encoder.", "globalizer.")) for k in changed)
    log = _log(out / "train_log.jsonl")
    assert [r["pair"] for r in log] == [0.0, 0.0] and log[0]["lr"] < log[1]["lr"]


@pytest.mark.parametrize(
    ("field", "value", "text"),
    [
        ("pair_weight", -1.0, "pair_weight must be >= 0, got -1.0"),
        ("warmup_steps", -1, "warmup_steps must be >= 0, got -1"),
        ("patch_weight", -0.5, "patch_weight must be >= 0, got -0.5"),
        ("patch_weight", float("nan"), "patch_weight must be >= 0, got nan"),
        ("pair_positives", "easy", "pair_positives must be 'hardest' or 'random', got 'easy'"),
        ("grey", 1.5, "grey=1.5: a probability, use a value in 0..1"),
        ("grey", float("nan"), r"grey=nan: a probability, use a value in 0..1"),
        ("grey_places", 1.5, "grey_places=1.5: a probability, use a value in 0..1"),
        ("grey_places", -0.1, "grey_places=-0.1: a probability, use a value in 0..1"),
        ("exposure", -0.1, r"exposure=-0.1: must be >= 0 \(0 = no gain jitter\)"),
    ],
)
def test_stage_two_rejects_negative_settings(
    tmp_path: Path, field: str, value: float, text: str
) -> None:
    cfg = Stage2Config(data=[], out_dir=tmp_path, **{field: value})
    with pytest.raises(ConfigError, match=f"^{text}$"):
        train_stage2(cfg)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One stage-one epoch, then one stage-two epoch from it with validation."""
    root = tmp_path_factory.mktemp("train")
    data = make_place_folders(root / "places", places=6, per_place=4)
    val = make_utm_eval_set(root / "val", places=3)
    s1 = train_stage1(
        Stage1Config(
            data=[f"folders:{data}"],
            out_dir=root / "s1",
            epochs=1,
            places_per_batch=3,
            warmup_steps=1,
            **TINY,
        )
    )
    s2 = train_stage2(
        Stage2Config(
            data=[str(data)],
            out_dir=root / "s2",
            init=s1,
            epochs=1,
            places_per_batch=3,
            val=(val,),
            **TINY,
        )
    )
    return {"root": root, "data": data, "s1": s1, "s2": s2}


def _log(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_stage_one_epoch_writes_checkpoints_and_log(trained: dict[str, Path]) -> None:
    out = trained["s1"].parent
    assert sorted(p.name for p in out.iterdir()) == [
        "epoch_000.pt",
        "last.pt",
        "stage1_final.pt",
        "train_log.jsonl",
    ]
    log = _log(out / "train_log.jsonl")
    assert [r["step"] for r in log] == [1, 2] and {"loss", "lr", "epoch"} <= set(log[0])
    state = read_training_state(out / "last.pt")
    assert (state["stage"], state["epoch"], state["batch"], state["step"]) == (1, 1, 0, 2)
    assert load_pairvpr(trained["s1"], with_stage1_head=True).config.with_stage1_head


def test_stage_two_epoch_starts_from_stage_one(trained: dict[str, Path]) -> None:
    one = load_pairvpr(trained["s1"])
    two = load_pairvpr(trained["s2"])
    assert not two.config.with_stage1_head
    block0 = "encoder.model.blocks.0.mlp.fc1.weight"  # frozen: tiny trains 1 of 2 blocks
    assert torch.equal(one.state_dict()[block0], two.state_dict()[block0])
    assert not torch.equal(one.decoder_clstoken, two.decoder_clstoken)  # re-initialised
    log = _log(trained["s2"].parent / "train_log.jsonl")
    assert {"global", "pair", "mined"} <= set(log[0])
    assert set(log[-1]["val"]["val"]) == {"R@1", "R@5", "R@10"}


def test_checkpoints_reload_with_identical_outputs(trained: dict[str, Path]) -> None:
    final = load_pairvpr(trained["s2"])
    last = load_pairvpr(trained["s2"].parent / "last.pt")
    images = torch.randn(2, 3, 56, 56)
    with torch.inference_mode():
        dense_a, desc_a = final.encode(images)
        dense_b, desc_b = last.encode(images)
        scores_a = final.pair_scores(dense_a[0], dense_a)
        scores_b = last.pair_scores(dense_b[0], dense_b)
    assert torch.equal(desc_a, desc_b) and torch.equal(scores_a, scores_b)
    path = trained["root"] / "again.pt"
    save_training_checkpoint(final, path, torch.optim.AdamW([torch.zeros(1)]), {"stage": 2})
    again = load_pairvpr(path)
    with torch.inference_mode():
        assert torch.equal(again.encode(images)[1], desc_a)


@pytest.mark.slow
def test_stage_one_resume_continues_mid_epoch(trained: dict[str, Path]) -> None:
    out = trained["root"] / "resume"
    cfg = Stage1Config(
        data=[str(trained["data"])], out_dir=out, epochs=1, places_per_batch=3, max_steps=1, **TINY
    )
    train_stage1(cfg)
    assert read_training_state(out / "last.pt")["batch"] == 1
    cfg.max_steps, cfg.resume = None, out / "last.pt"
    train_stage1(cfg)
    assert [r["step"] for r in _log(out / "train_log.jsonl")] == [1, 2]
    assert read_training_state(out / "last.pt")["step"] == 2


def test_resume_refuses_the_other_stages_checkpoint(trained: dict[str, Path]) -> None:
    data, out = [str(trained["data"])], trained["root"] / "wrong_stage"
    one, two = trained["s1"].parent / "last.pt", trained["s2"].parent / "last.pt"
    with pytest.raises(TrainingError, match=f"^{two} is a stage-2 checkpoint, not stage 1$"):
        train_stage1(Stage1Config(data=data, out_dir=out, resume=two, **TINY))
    with pytest.raises(TrainingError, match=f"^{one} is a stage-1 checkpoint, not stage 2$"):
        train_stage2(Stage2Config(data=data, out_dir=out, resume=one, **TINY))
    assert not out.exists()


def test_stage_one_starts_from_dinov2_weights(trained: dict[str, Path]) -> None:
    backbone = build_pairvpr(ModelConfig.tiny(), seed=5).encoder.model.state_dict()
    path = trained["root"] / "dinov2_tiny_reg4.pth"
    torch.save(backbone, path)
    out = trained["root"] / "dino"
    final = train_stage1(
        Stage1Config(
            data=[str(trained["data"])],
            out_dir=out,
            dinov2=path,
            places_per_batch=3,
            max_steps=1,
            **TINY,
        )
    )
    got = load_pairvpr(final).state_dict()
    for name in ("pos_embed", "blocks.0.attn.qkv.weight", "register_tokens"):  # all frozen
        assert torch.equal(got[f"encoder.model.{name}"], backbone[name]), name
    assert not torch.equal(
        got["encoder.model.blocks.1.attn.qkv.weight"], backbone["blocks.1.attn.qkv.weight"]
    )


def test_non_finite_loss_stops_training(trained: dict[str, Path], tmp_path: Path) -> None:
    model = build_pairvpr(ModelConfig.tiny(), seed=0)
    dataset = PlaceImagesDataset(load_place_folders(trained["data"]), 2, size=56)
    sampler = PlaceBatchSampler(len(dataset), 2)
    loader = make_loader(dataset, sampler, workers=0, pin=False)
    weight = model.globalizer[0].weight
    settings = LoopSettings(
        out_dir=tmp_path, stage=2, epochs=1, base_lr=1e-3, lr_factor=lambda s: 1.0, log_every=1
    )
    job = LoopJob(
        ctx=DistContext(),
        model=model,
        optimizer=torch.optim.AdamW([weight]),
        step=lambda batch: {"loss": weight.sum() * float("nan")},
        data=PlaceData(dataset, sampler, loader),
        settings=settings,
    )
    with pytest.raises(TrainingError, match=r"stage 2 loss is not finite at step 0: lower the"):
        run_loop(job, Progress())


def test_cli_reports_bad_dataset_path(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    argv = [
        "--data",
        f"gsv:{tmp_path / 'gsv'}",
        "--out",
        str(tmp_path),
        "--arch",
        "tiny",
        "--device",
        "cpu",
    ]
    assert stage2.main(argv) == 1  # bad data: pair_vpr_ros.cli's code 1
    assert capsys.readouterr().err.startswith(f"error: dataset folder {tmp_path / 'gsv'}/Datafr")
    assert (
        stage1.main(argv[:2] + ["--out", str(tmp_path), "--arch", "tiny", "--image-size", "50"])
        == 1
    )
    assert "image_size=50 is not a positive multiple of 14" in capsys.readouterr().err


def test_cli_ctrl_c_says_how_to_resume(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupted(stage: object) -> Path:
        raise KeyboardInterrupt

    monkeypatch.setattr(driver, "train", interrupted)
    assert stage1.main(["--data", "d", "--out", str(tmp_path)]) == 130
    assert capsys.readouterr().err == "error: interrupted; resume with --resume <out>/last.pt\n"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _torchrun(module: str, args: list[str]) -> None:
    """Two ranks on gloo over loopback."""
    env = dict(os.environ, OMP_NUM_THREADS="1", GLOO_SOCKET_IFNAME="lo", MASTER_ADDR="127.0.0.1")
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node",
        "2",
        "--master_addr",
        "127.0.0.1",
        "--master_port",
        str(_free_port()),
        "-m",
        module,
        *args,
    ]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.mark.slow
def test_two_process_gloo_matches_one_process(trained: dict[str, Path]) -> None:
    """torchrun, 2 ranks: a stage-one and a stage-two step; two ranks x 2 places take the same
    stage-two optimiser step as one process x 4 places."""
    root, data = trained["root"] / "ddp", str(trained["data"])
    common = [
        "--data",
        data,
        "--arch",
        "tiny",
        "--image-size",
        "56",
        "--workers",
        "0",
        "--device",
        "cpu",
        "--max-steps",
        "1",
        "--places-per-batch",
        "2",
    ]
    _torchrun("pair_vpr_ros.learn.train.stage1", [*common, "--out", str(root / "s1")])
    assert read_training_state(root / "s1" / "last.pt")["step"] == 1
    _torchrun(
        "pair_vpr_ros.learn.train.stage2",
        [*common, "--out", str(root / "s2"), "--images-per-place", "2"],
    )
    cfg = Stage2Config(
        data=[data],
        out_dir=root / "one",
        max_steps=1,
        places_per_batch=4,
        images_per_place=2,
        **TINY,
    )
    two, one = load_pairvpr(root / "s2" / "stage2_final.pt"), load_pairvpr(train_stage2(cfg))
    for name, tensor in one.state_dict().items():
        assert torch.allclose(two.state_dict()[name], tensor, atol=1e-6), name
    loss_two = _log(root / "s2" / "train_log.jsonl")[0]["loss"]
    assert loss_two == pytest.approx(_log(root / "one" / "train_log.jsonl")[0]["loss"], rel=1e-5)


def test_cli_flags_defaults_and_values(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Every flag lands in its config field; the defaults are the stages' own."""
    common = {
        "--arch": ("tiny", "arch", "tiny"),
        "--image-size": ("56", "image_size", 56),
        "--dinov2": ("d.pth", "dinov2", Path("d.pth")),
        "--train-blocks": ("1", "train_blocks", 1),
        "--epochs": ("3", "epochs", 3),
        "--max-steps": ("7", "max_steps", 7),
        "--places-per-batch": ("5", "places_per_batch", 5),
        "--lr": ("0.5", "lr", 0.5),
        "--weight-decay": ("0.1", "weight_decay", 0.1),
        "--grad-clip": ("0", "grad_clip", 0.0),
        "--workers": ("0", "workers", 0),
        "--device": ("cpu", "device", "cpu"),
        "--seed": ("4", "seed", 4),
        "--save-every": ("9", "save_every", 9),
        "--checkpoint-every": ("0", "checkpoint_every", 0),
        "--log-every": ("2", "log_every", 2),
        "--resume": ("r.pt", "resume", Path("r.pt")),
        "--warmup-steps": ("6", "warmup_steps", 6),
        "--grey": ("0.5", "grey", 0.5),
        "--grey-places": ("0.5", "grey_places", 0.5),
        "--exposure": ("0.3", "exposure", 0.3),
        "--conditions": ("3", "conditions", 3),
    }
    own = {
        stage1: {
            "--mask-ratio": ("0.5", "mask_ratio", 0.5),
            "--min-lr": ("0.1", "min_lr", 0.1),
            "--layer-decay": ("0.75", "layer_decay", 0.75),
            "--weight-decay-end": ("0.3", "weight_decay_end", 0.3),
        },
        stage2: {
            "--init": ("i.pt", "init", Path("i.pt")),
            "--images-per-place": ("3", "images_per_place", 3),
            "--end-lr-factor": ("0.5", "end_lr_factor", 0.5),
            "--pair-weight": ("0", "pair_weight", 0.0),
            "--pair-directions": ("first", "pair_directions", "first"),
            "--patch-weight": ("1.5", "patch_weight", 1.5),
            "--pair-positives": ("random", "pair_positives", "random"),
            "--val-rerank-k": ("5", "val_rerank_k", 5),
            "--twin-share": ("0.25", "twin_share", 0.25),
            "--pair-negatives": ("random", "pair_negatives", "random"),
            "--heldout": ("h", "heldout", Path("h")),
            "--eval-every": ("50", "eval_every", 50),
        },
    }
    required = ["--data", "a", "--data", "gsv:b", "--out", "o"]
    defaults = {
        stage1: Stage1Config(data=["a", "gsv:b"], out_dir=Path("o")),
        stage2: Stage2Config(data=["a", "gsv:b"], out_dir=Path("o")),
    }
    switches = ["--no-amp", "--no-augment"]
    repeated = {stage1: [], stage2: ["--val", "v", "--val", "w"]}
    for module, config in ((stage1, Stage1Config), (stage2, Stage2Config)):
        flags = {**common, **own[module]}
        parser = module.build_parser()
        listed = {s for a in parser._actions for s in a.option_strings} - {"-h", "--help"}
        assert listed == {*flags, *switches, *repeated[module][:1], "--data", "--out"}
        assert config_from_args(config, parser.parse_args(required)) == defaults[module]
        argv = [*required, *switches, *repeated[module]]
        argv += [x for flag, (value, _, _) in flags.items() for x in (flag, value)]
        cfg = config_from_args(config, parser.parse_args(argv))
        for flag, (_, name, value) in flags.items():
            assert getattr(cfg, name) == value, flag
        assert not cfg.amp and not cfg.augment
    assert cfg.val == (Path("v"), Path("w"))
    d1, d2 = defaults[stage1], defaults[stage2]
    assert (d1.image_size, d1.places_per_batch, d1.lr, d1.warmup_steps) == (224, 64, None, 1000)
    # the authors' stage-one recipe
    assert (d1.layer_decay, d1.weight_decay, d1.weight_decay_end) == (0.9, 0.04, 0.4)
    assert (d1.min_lr, d1.grad_clip, d2.grad_clip) == (1e-6, 0.0, 1.0)
    assert Stage1(d1).base_lr(DistContext(world_size=2)) == pytest.approx(
        3e-4 * (128 / 1024) ** 0.5
    )
    assert (d2.image_size, d2.places_per_batch, d2.lr, d2.warmup_steps) == (322, 30, 8e-5, 0)
    assert (d1.arch, d1.epochs, d1.workers, d1.device, d1.amp, d2.val) == (
        "B",
        10,
        4,
        "auto",
        True,
        (),
    )
    assert stage1.main(["--help"]) == 0
    assert "training image size in pixels, a multiple of 14 (default 224)" in " ".join(
        capsys.readouterr().out.split()
    )
    assert stage2.main(["--out", "o"]) == 2  # usage: --data is required
    assert "the following arguments are required: --data" in capsys.readouterr().err
