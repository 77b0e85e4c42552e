"""Stage one: Siamese masked image modelling with place-aware pair sampling.

Two images of one place; 90% of the first image's patches are replaced by the encoder's mask
token (a fresh random choice per image); the encoder sees the masked first and the full second
image in one batch; the decoder (no class token) cross-attends from the first to the second;
`prediction_head` predicts every patch's 14x14x3 pixels and the loss is the MSE over masked
patches against per-patch normalised targets.

Optimiser as the authors publish it: AdamW, betas (0.9, 0.999), peak lr 3e-4 x sqrt(global
batch / 1024) after a linear warm-up, cosine to 1e-6, layer-wise lr decay 0.9 over the encoder
and the decoder together, weight decay on a cosine from 0.04 to 0.4, no gradient clipping, the
encoder's mask token fixed. The decoder's position table is the true sine-cosine table of the
training grid (16x16 at 224 px); stage two stretches it to its own grid. Run with
``torchrun --nproc_per_node N -m pair_vpr_ros.learn.train.stage1 ...`` for DDP.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor, nn

from pair_vpr_ros.learn.train.common import DistContext, cosine, param_groups, warmup_cosine
from pair_vpr_ros.learn.train.config import TrainConfig
from pair_vpr_ros.learn.train.driver import Stage, stage_main, stage_parser, train
from pair_vpr_ros.learn.train.loop import StepFn
from pair_vpr_ros.learn.train.losses import masked_patch_mse, random_patch_mask
from pair_vpr_ros.learn.train.options import option, redefault
from pair_vpr_ros.model import ModelConfig, PairVPR


@dataclass
class Stage1Config(TrainConfig):
    """Stage-one settings; defaults follow the paper where it gives them (224 px, 90% masking,
    half of the encoder trained), the rest are ours."""

    image_size: int = redefault(TrainConfig, "image_size", 224)
    places_per_batch: int = redefault(TrainConfig, "places_per_batch", 64)  # pairs per process
    lr: float | None = option(
        None, "peak learning rate (default: 3e-4 x sqrt(global batch / 1024), the authors' rule)"
    )
    weight_decay: float = redefault(TrainConfig, "weight_decay", 0.04)
    weight_decay_end: float = option(
        0.4, "weight decay follows a cosine from --weight-decay to this (default %(default)s)"
    )
    grad_clip: float = redefault(TrainConfig, "grad_clip", 0.0)
    mask_ratio: float = option(0.9, "fraction of first-image patches masked (default %(default)s)")
    min_lr: float = option(1e-6, "the cosine ends at this learning rate (default %(default)s)")
    warmup_steps: int = option(
        1000, "linear warm-up steps, at most a tenth of the run (default %(default)s)"
    )
    layer_decay: float = option(
        0.9,
        "layer-wise lr decay over encoder and decoder blocks together: layer i of L gets "
        "lr * decay**(L + 1 - i) (default %(default)s)",
    )


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
        decoded = self.model.decode(masked, unmasked, use_cls=False)
        return masked_patch_mse(self.model.prediction_head(decoded), first, mask)


class Stage1(Stage):
    """Masked reconstruction of the first image of each pair (see the module docstring)."""

    number = 1
    config_class = Stage1Config
    with_stage1_head = True
    cfg: Stage1Config
    _world = 1  # processes, known once the objective is made

    @property
    def images_per_place(self) -> int:
        return 2

    def model_config(self) -> ModelConfig:
        """As the driver's, with the decoder's position table built at the training grid."""
        mcfg = super().model_config()
        return replace(mcfg, dec_pos_grid=mcfg.grid)

    def base_lr(self, ctx: DistContext) -> float:
        if self.cfg.lr is not None:
            return self.cfg.lr
        return 3e-4 * math.sqrt(self.cfg.places_per_batch * ctx.world_size / 1024)

    def optimizer(self, model: PairVPR) -> torch.optim.Optimizer:
        groups = param_groups(
            model, self.cfg.weight_decay, self.cfg.layer_decay, with_decoder=True
        )
        return torch.optim.AdamW(groups, lr=1e-3, betas=(0.9, 0.999))  # lr set every step

    def lr_factor(self, step: int, total: int) -> float:
        warmup = min(self.cfg.warmup_steps, total // 10 + 1)
        peak = self.base_lr(DistContext(world_size=self._world))
        return warmup_cosine(step, total, warmup, min(1.0, self.cfg.min_lr / peak))

    def weight_decay_at(self, step: int, total: int) -> float:
        return cosine(step, total, self.cfg.weight_decay, self.cfg.weight_decay_end)

    def objective(self, model: PairVPR, ctx: DistContext) -> nn.Module:
        self._world = ctx.world_size
        return Stage1Objective(model)

    def make_step(self, objective: nn.Module, model: PairVPR, ctx: DistContext) -> StepFn:
        masks = torch.Generator().manual_seed(self.cfg.seed * 7919 + ctx.rank + 1)
        ratio = self.cfg.mask_ratio

        def step(batch: tuple[Tensor, ...]) -> dict[str, Tensor]:
            images = batch[0].to(ctx.device, non_blocking=True)
            mask = random_patch_mask(images.shape[0], model.num_patches, ratio, masks)
            return {"loss": objective(images[:, 0], images[:, 1], mask.to(ctx.device))}

        return step


def train_stage1(cfg: Stage1Config) -> Path:
    """Train stage one; returns the path of the final weights (``<out>/stage1_final.pt``)."""
    return train(Stage1(cfg))


def build_parser() -> argparse.ArgumentParser:
    return stage_parser(
        Stage1Config,
        prog="pairvpr-train-stage1",
        description="Pair-VPR stage one: Siamese masked image modelling on place pairs. "
        "Multi-GPU: torchrun --nproc_per_node N -m pair_vpr_ros.learn.train.stage1 ...",
    )


def main(argv: list[str] | None = None) -> int:
    return stage_main(Stage1, build_parser(), argv)


if __name__ == "__main__":
    raise SystemExit(main())
