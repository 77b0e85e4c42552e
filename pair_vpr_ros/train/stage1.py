"""Stage one: Siamese masked image modelling with place-aware pair sampling.

Two images of one place; 90% of the first image's patches are replaced by the encoder's mask
token (a fresh random choice per image); the encoder sees the masked first and the full second
image in one batch; the decoder (no class token) cross-attends from the first to the second;
`prediction_head` predicts every patch's 14x14x3 pixels and the loss is the MSE over masked
patches against per-patch normalised targets. AdamW with layer-wise lr decay, linear warm-up,
cosine decay. Run with ``torchrun --nproc_per_node N -m pair_vpr_ros.train.stage1 ...`` for DDP.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel

from pair_vpr_ros.datasets import concat_collections, load_places
from pair_vpr_ros.errors import TrainingError
from pair_vpr_ros.model import (
    ModelConfig,
    build_pairvpr,
    load_dinov2_encoder,
    load_pairvpr,
    save_pairvpr,
)
from pair_vpr_ros.train.cli import add_common_args, common_config, run
from pair_vpr_ros.train.common import (
    DistContext,
    init_distributed,
    load_optimizer,
    param_groups,
    plain_config,
    read_training_state,
    set_trainable,
    shutdown_distributed,
    warmup_cosine,
)
from pair_vpr_ros.train.data import (
    AugmentConfig,
    PlaceBatchSampler,
    PlaceImagesDataset,
    make_loader,
)
from pair_vpr_ros.train.loop import LoopSettings, Progress, run_loop
from pair_vpr_ros.train.losses import masked_patch_mse, random_patch_mask


@dataclass
class Stage1Config:
    """Stage-one settings; defaults follow the paper where it gives them (224 px, 90% masking,
    half of the encoder trained), the rest are ours."""

    data: list[str]  # "KIND:ROOT" place collections (see pair_vpr_ros.datasets)
    out_dir: Path
    arch: str = "B"
    image_size: int = 224
    dinov2: Path | None = None  # DINOv2 *_reg4 weights for the encoder; random init if None
    train_blocks: int | None = None  # last N encoder blocks train; None: half the depth
    epochs: int = 10
    max_steps: int | None = None
    places_per_batch: int = 64  # pairs per batch on each process
    mask_ratio: float = 0.9
    lr: float = 2e-4
    min_lr_factor: float = 0.01  # cosine floor as a fraction of lr
    warmup_steps: int = 1000  # linear warm-up, capped at a tenth of the run
    weight_decay: float = 0.05
    layer_decay: float = 0.75
    grad_clip: float = 1.0
    workers: int = 4
    device: str = "auto"
    amp: bool = True
    augment: bool = True
    seed: int = 0
    save_every: int = 1000
    checkpoint_every: int = 1
    log_every: int = 10
    resume: Path | None = None


class Stage1Objective(nn.Module):
    """(first [B,3,H,W], second [B,3,H,W], mask [B,N] bool) -> masked reconstruction loss."""

    def __init__(self, model: nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, first: Tensor, second: Tensor, mask: Tensor) -> Tensor:
        both = torch.cat([first, second])
        full = torch.cat([mask, torch.zeros_like(mask)])
        dense = self.model.encoder.forward_features(both, mask=full)["dense"]
        masked, unmasked = dense.split(first.shape[0])
        decoded = self.model.decoder.forward_tokens(masked, unmasked, use_cls=False)
        return masked_patch_mse(self.model.prediction_head(decoded), first, mask)


def _build_model(cfg: Stage1Config, ctx: DistContext) -> tuple[nn.Module, dict | None]:
    if cfg.resume is not None:
        state = read_training_state(cfg.resume)
        if state["stage"] != 1:
            raise TrainingError(
                f"{cfg.resume} is a stage-{state['stage']} checkpoint, not stage 1"
            )
        model = load_pairvpr(cfg.resume, device=ctx.device, with_stage1_head=True)
        if not model.config.with_stage1_head:
            raise TrainingError(f"{cfg.resume} has no prediction_head: not a stage-one checkpoint")
        return model, state
    mcfg = ModelConfig.preset(cfg.arch, image_size=cfg.image_size, with_stage1_head=True)
    model = build_pairvpr(mcfg, seed=cfg.seed)  # same init on every rank
    if cfg.dinov2 is not None:
        missing = load_dinov2_encoder(model, cfg.dinov2)
        if missing and ctx.is_main:
            print(f"note: {cfg.dinov2} lacks {missing}; they keep their random init")
    return model.to(ctx.device), None


def train_stage1(cfg: Stage1Config) -> Path:
    """Train stage one; returns the path of the final weights (``<out>/stage1_final.pt``)."""
    if cfg.resume is None:  # a bad size or preset fails now, before datasets are scanned
        ModelConfig.preset(cfg.arch, image_size=cfg.image_size)
    ctx = init_distributed(cfg.device)
    try:
        return _train(cfg, ctx)
    finally:
        shutdown_distributed(ctx)


def _train(cfg: Stage1Config, ctx: DistContext) -> Path:
    places = concat_collections([load_places(spec) for spec in cfg.data])
    model, state = _build_model(cfg, ctx)
    depth = model.config.depth
    set_trainable(model, 1, cfg.train_blocks or max(1, depth // 2))
    optimizer = torch.optim.AdamW(
        param_groups(model, cfg.weight_decay, cfg.layer_decay), lr=cfg.lr, betas=(0.9, 0.95)
    )
    progress = Progress()
    if state is not None:
        load_optimizer(optimizer, state, cfg.resume)
        progress = Progress(int(state["epoch"]), int(state["batch"]), int(state["step"]))
    size = model.config.image_size
    augment = AugmentConfig() if cfg.augment else None
    dataset = PlaceImagesDataset(places, 2, size, augment, seed=cfg.seed)
    sampler = PlaceBatchSampler(
        len(dataset), cfg.places_per_batch, ctx.rank, ctx.world_size, cfg.seed
    )
    loader = make_loader(dataset, sampler, cfg.workers, ctx.device.type == "cuda")
    objective: nn.Module = Stage1Objective(model)
    if ctx.distributed:
        ids = [ctx.device.index] if ctx.device.type == "cuda" else None
        objective = DistributedDataParallel(objective, device_ids=ids)
    total = cfg.max_steps or cfg.epochs * len(sampler)
    masks = torch.Generator().manual_seed(cfg.seed * 7919 + ctx.rank + 1)

    def step(batch: tuple[Tensor, ...]) -> dict[str, Tensor]:
        images = batch[0].to(ctx.device, non_blocking=True)
        mask = random_patch_mask(images.shape[0], model.num_patches, cfg.mask_ratio, masks)
        return {"loss": objective(images[:, 0], images[:, 1], mask.to(ctx.device))}

    settings = LoopSettings(
        out_dir=cfg.out_dir,
        stage=1,
        epochs=cfg.epochs,
        base_lr=cfg.lr,
        lr_factor=lambda s: warmup_cosine(
            s, total, min(cfg.warmup_steps, total // 10 + 1), cfg.min_lr_factor
        ),
        max_steps=cfg.max_steps,
        grad_clip=cfg.grad_clip,
        amp=cfg.amp,
        save_every=cfg.save_every,
        checkpoint_every=cfg.checkpoint_every,
        log_every=cfg.log_every,
        config=plain_config(cfg),
    )
    run_loop(ctx, model, step, optimizer, dataset, sampler, loader, settings, progress)
    final = cfg.out_dir / "stage1_final.pt"
    if ctx.is_main:
        save_pairvpr(model, final, extra={"stage": 1})
    return final


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pairvpr-train-stage1",
        description="Pair-VPR stage one: Siamese masked image modelling on place pairs. "
        "Multi-GPU: torchrun --nproc_per_node N -m pair_vpr_ros.train.stage1 ...",
    )
    add_common_args(parser, image_size=224, epochs=10, places=64)
    add = parser.add_argument
    add("--mask-ratio", type=float, default=0.9, help="fraction of first-image patches masked")
    add("--lr", type=float, default=2e-4, help="peak learning rate (default 2e-4)")
    add("--min-lr-factor", type=float, default=0.01, help="cosine floor as a fraction of --lr")
    add(
        "--warmup-steps",
        type=int,
        default=1000,
        help="linear warm-up steps, at most a tenth of the run (default 1000)",
    )
    add(
        "--layer-decay",
        type=float,
        default=0.75,
        help="layer-wise lr decay: block i of depth L gets lr * decay**(L - i) (default 0.75)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    cfg = Stage1Config(
        **common_config(args),
        mask_ratio=args.mask_ratio,
        lr=args.lr,
        min_lr_factor=args.min_lr_factor,
        warmup_steps=args.warmup_steps,
        layer_decay=args.layer_decay,
    )
    return run(lambda: train_stage1(cfg))


if __name__ == "__main__":
    raise SystemExit(main())
