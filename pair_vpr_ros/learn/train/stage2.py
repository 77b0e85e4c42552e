"""Stage two: joint training of the global descriptor and the pair classifier.

Batches of P places x 4 images (GSV-Cities). Global loss: multi-similarity (alpha 1, beta 50,
base 0, dot product) on pairs from the multi-similarity miner (epsilon 0.1), computed over the
global batch (descriptors all-gathered across processes). Pair loss: for each local anchor the
hardest positive and hardest negative of the global batch by descriptor similarity; binary
cross-entropy pushes logit(anchor, positive) to 1 and logit(anchor, negative) to 0. With
``pair_directions="both"`` (default) each pair is also scored with the other image first
(logit(positive, anchor) -> 1, logit(negative, anchor) -> 0): inference sums both directions, so
both are trained. The network spec does not say which of the two the paper used; "first" trains
the anchor-first direction only. Total = global + 2.0 * pair. AdamW lr 8e-5, weight decay 0.05,
lr falling linearly to 0.2x; the last half of the encoder blocks train.

Options beyond the paper, for the demo model: a linear lr warm-up; ``pair_weight=0`` (global
descriptor alone: an encoder pre-training in place of DINOv2); ``patch_weight`` (multi-similarity
on each image's mean dense token, so the tokens the pair classifier reads carry the place);
``pair_positives`` / ``pair_negatives="random"``; ``conditions`` (issue 24: positive and negative
share their lighting relation to the anchor, in equal shares, so "other lighting" cannot
separate them, `relation_hard_indices`); ``twin_share`` (identical and near-identical pairs as
positives, balanced by same-lighting negatives, so that a repeat outscores a revisit).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.learn.eval_sets import load_eval_set
from pair_vpr_ros.learn.heldout import HeldoutViews
from pair_vpr_ros.learn.train.common import DistContext, gather_batch, linear_decay, param_groups
from pair_vpr_ros.learn.train.config import TrainConfig
from pair_vpr_ros.learn.train.curves import heldout_hook, validate
from pair_vpr_ros.learn.train.data import near_identical
from pair_vpr_ros.learn.train.driver import Stage, stage_main, stage_parser, train
from pair_vpr_ros.learn.train.loop import StepFn
from pair_vpr_ros.learn.train.losses import (
    MultiSimilarityObjective,
    batch_hard_indices,
    pair_bce,
    random_positive_indices,
    relation_hard_indices,
    same_condition_negatives,
)
from pair_vpr_ros.learn.train.options import option, redefault
from pair_vpr_ros.model import PairVPR, load_pairvpr
from pair_vpr_ros.model.checkpoint import STAGE2_NEW


@dataclass
class Stage2Config(TrainConfig):
    """Stage-two settings; defaults are the paper's where it gives them. ``arch`` and
    ``dinov2`` apply only without ``init`` and ``resume``."""

    places_per_batch: int = redefault(TrainConfig, "places_per_batch", 30)
    lr: float = redefault(TrainConfig, "lr", 8e-5)
    init: Path | None = option(
        None, "stage-one checkpoint (stage1_final.pt) or any Pair-VPR weights to start from"
    )
    images_per_place: int = option(4, "images of each place per batch (default %(default)s)")
    end_lr_factor: float = option(
        0.2, "the lr falls linearly to this fraction of --lr at the end (default %(default)s)"
    )
    warmup_steps: int = option(
        0,
        "raise the lr linearly from 0 over this many steps first (default %(default)s, as the "
        "paper); from a random init a warm-up keeps the global descriptor from collapsing early",
    )
    pair_weight: float = option(
        2.0,
        "weight of the pair loss (default %(default)s); 0 trains the global descriptor alone, "
        "without running the decoder",
    )
    patch_weight: float = option(
        0.0,
        "weight of a multi-similarity loss on each image's mean dense token, which teaches the "
        "tokens the pair classifier reads the place (default %(default)s: off, as the paper)",
    )
    pair_positives: str = option(
        "hardest",
        "positive of each anchor in the pair loss: the hardest by descriptor (default, as the "
        "paper) or a random one of the same place",
        choices=("hardest", "random"),
    )
    pair_directions: str = option(
        "both",
        "train the pair logits in both image orders (default) or anchor-first only",
        choices=("both", "first"),
    )
    pair_negatives: str = option(
        "hardest",
        "negative of each anchor in the pair loss with --conditions: the hardest by descriptor "
        "(default, as the paper) or a random one of another place (an easier start)",
        choices=("hardest", "random"),
    )
    twin_share: float = option(
        0.0,
        "for this share of each batch also train the image against itself and against a "
        "near-identical copy (2 px shift, +-2 grey levels) as the same place, so that a repeat "
        "scores at least as high as a revisit (default %(default)s)",
    )
    heldout: Path | None = option(
        None, "held-out place folders (ROOT/<place>/<k>.png) to measure re-ranked vs global AP on"
    )
    eval_every: int = option(
        0, "measure on --heldout every N steps and redraw curves.png (default %(default)s: never)"
    )
    val: tuple[Path, ...] = option(
        (), "validation set root (database/ + queries/), repeatable; Recall@N each epoch"
    )
    val_rerank_k: int = option(
        0, "also report re-ranked validation recall with this K (default 0: global only)"
    )
    ms_alpha: float = 1.0  # multi-similarity loss and miner: the paper's values, no flags
    ms_beta: float = 50.0
    ms_base: float = 0.0
    miner_epsilon: float = 0.1


class Stage2Objective(nn.Module):
    """(images [B,3,S,S], labels [B], conditions [B] or None) -> {"loss", "global", "patch",
    "pair", "pair_rank", "mined"} over the global batch. Lives inside DDP so every collective
    and parameter use happens in one forward."""

    def __init__(self, model: PairVPR, cfg: Stage2Config, ctx: DistContext) -> None:
        super().__init__()
        self.model, self.ctx = model, ctx
        self.pair_weight, self.both = cfg.pair_weight, cfg.pair_directions == "both"
        self.patch_weight, self.random_positive = cfg.patch_weight, cfg.pair_positives == "random"
        self.twin_share, self.by_condition = cfg.twin_share, cfg.conditions > 0
        self.random_negative = cfg.pair_negatives == "random"
        self.metric = MultiSimilarityObjective(
            cfg.ms_alpha, cfg.ms_beta, cfg.ms_base, cfg.miner_epsilon
        )

    def forward(
        self, images: Tensor, labels: Tensor, conds: Tensor | None = None
    ) -> dict[str, Tensor]:
        b = images.shape[0]
        twins = self.twin_count(b)
        if twins:  # near-identical copies of the first anchors, encoded in the same pass
            images = torch.cat([images, near_identical(images[:twins])])
        dense, desc = self.model.encode(images)
        dense, twin_dense, desc = dense[:b], dense[b:], desc[:b]
        desc_all = gather_batch(desc.float(), self.ctx)
        labels_all = gather_batch(labels, self.ctx)
        with torch.autocast(desc.device.type, enabled=False):  # beta=50 needs float32
            global_loss, mined = self.metric(desc_all, labels_all)
            patch_loss = global_loss.new_zeros(())
            if self.patch_weight > 0:
                pooled = F.normalize(dense.float().mean(dim=1), dim=-1)  # [B,D]
                patch_loss = self.metric(gather_batch(pooled, self.ctx), labels_all)[0]
        terms = {
            "global": global_loss.detach(),
            "patch": patch_loss.detach(),
            "pair": global_loss.new_zeros(()),
            "pair_rank": global_loss.new_zeros(()),
            "mined": torch.tensor(float(mined)),
        }
        loss = global_loss + self.patch_weight * patch_loss
        if self.pair_weight == 0:  # global descriptor only: the decoder is frozen and not run
            return {"loss": loss, **terms}
        pair_loss, rank = self.pair_loss(dense, twin_dense, desc, desc_all, labels, conds)
        terms.update(pair=pair_loss.detach(), pair_rank=rank)
        return {"loss": loss + self.pair_weight * pair_loss, **terms}

    def twin_count(self, batch: int) -> int:
        on = self.pair_weight > 0 and self.twin_share > 0
        return max(1, round(self.twin_share * batch)) if on else 0

    def pair_loss(
        self,
        dense: Tensor,
        twin_dense: Tensor,
        desc: Tensor,
        desc_all: Tensor,
        labels: Tensor,
        conds: Tensor | None,
    ) -> tuple[Tensor, Tensor]:
        """BCE of the pair logits on mined (anchor, positive) -> 1, (anchor, negative) -> 0,
        identical / near-identical pairs -> 1 and as many same-lighting other-place pairs -> 0;
        also the share of anchors whose positive outscores their negative."""
        labels_all = gather_batch(labels, self.ctx)
        own = self.ctx.rank * labels.shape[0] + torch.arange(labels.shape[0], device=labels.device)
        with torch.no_grad():
            sim = desc.detach().float() @ desc_all.detach().T
            conds_all = gather_batch(conds, self.ctx) if conds is not None else None
            if self.by_condition and conds is not None:
                pos, neg, valid = relation_hard_indices(
                    sim, labels, labels_all, own, conds, conds_all, self.random_negative
                )
            else:
                pos, neg, valid = batch_hard_indices(sim, labels, labels_all, own)
            if self.random_positive:
                pos = random_positive_indices(labels, labels_all, own)
            t = twin_dense.shape[0]
            firsts = slice(0, t)
            twin_neg = same_condition_negatives(
                labels[firsts], labels_all, None if conds is None else conds[firsts], conds_all
            )
        dense_all = gather_batch(dense, self.ctx)
        anchor, positive, negative = dense[valid], dense_all[pos[valid]], dense_all[neg[valid]]
        a = anchor.shape[0]
        first, second = [anchor, anchor], [positive, negative]
        if self.both:
            first, second = first + [positive, negative], second + [anchor, anchor]
        if t:  # identical and near-identical, both orders, and as many same-lighting negatives
            other = dense_all[twin_neg]
            first += [dense[:t], twin_dense, dense[:t], dense[:t], twin_dense, other]
            second += [dense[:t], dense[:t], twin_dense, other, other, dense[:t]]
        logits = self.model.pair_logits(torch.cat(first), torch.cat(second))
        mined = (4 if self.both else 2) * a
        # Rows: (anchor, positive), (anchor, negative)[, (positive, anchor), (negative, anchor)].
        pair, twins = logits[:mined].view(-1, a), logits[mined:].view(2, -1)
        pos_logits = torch.cat([pair[0::2].flatten(), twins[0]])
        neg_logits = torch.cat([pair[1::2].flatten(), twins[1]])
        rank = (pair[0] > pair[1]).float().mean().detach() if a else logits.new_zeros(())
        return pair_bce(pos_logits, neg_logits), rank


class Stage2(Stage):
    """Global descriptor + pair classifier (see the module docstring)."""

    number = 2
    config_class = Stage2Config
    cfg: Stage2Config

    @property
    def images_per_place(self) -> int:
        return self.cfg.images_per_place

    @property
    def pair_conditions(self) -> bool:
        return self.cfg.conditions > 0

    @property
    def trains_decoder(self) -> bool:
        # pair_weight 0: the decoder never runs, so it stays frozen (DDP must not wait for it)
        return self.cfg.pair_weight > 0

    def check(self) -> None:
        cfg = self.cfg
        if cfg.pair_directions not in ("both", "first"):
            raise ConfigError(
                f"pair_directions must be 'both' or 'first', got {cfg.pair_directions!r}"
            )
        if cfg.pair_negatives not in ("hardest", "random"):
            raise ConfigError(
                f"pair_negatives must be 'hardest' or 'random', got {cfg.pair_negatives!r}"
            )
        if cfg.pair_positives not in ("hardest", "random"):
            raise ConfigError(
                f"pair_positives must be 'hardest' or 'random', got {cfg.pair_positives!r}"
            )
        if not 0.0 <= cfg.twin_share <= 1.0:
            raise ConfigError(f"twin_share={cfg.twin_share}: a share of the batch, use 0..1")
        if cfg.eval_every < 0:
            raise ConfigError(f"eval_every={cfg.eval_every}: must be >= 0 (0 = never)")
        for name in ("pair_weight", "patch_weight"):
            if not getattr(cfg, name) >= 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(cfg, name)}")
        if cfg.warmup_steps < 0:
            raise ConfigError(f"warmup_steps must be >= 0, got {cfg.warmup_steps}")
        if cfg.images_per_place < 2:
            raise ConfigError("images_per_place must be >= 2 (positives come from the same place)")
        super().check()

    def prepare(self, ctx: DistContext) -> None:
        if self.cfg.places_per_batch * ctx.world_size < 2:
            raise ConfigError(
                "a global batch needs >= 2 places (negatives): raise --places-per-batch"
            )
        for root in self.cfg.val:  # fail before training, not after the first epoch
            load_eval_set(root)
        if self.cfg.heldout is not None and self.cfg.eval_every > 0:
            HeldoutViews.load(self.cfg.heldout)

    def start_model(self, ctx: DistContext) -> PairVPR:
        """Init checkpoint > random (+ DINOv2) init. A stage-one init gets fresh stage-two
        heads: `decoder_clstoken` ~ N(0, 1e-6), new `globalizer` and `classvprmodule`."""
        cfg = self.cfg
        if cfg.init is None:
            return super().start_model(ctx)
        source = load_pairvpr(
            cfg.init, image_size=cfg.image_size, allow_missing=STAGE2_NEW, with_stage1_head=True
        )
        if not source.config.with_stage1_head:  # a stage-two or released model: fine-tune it
            return source.to(ctx.device)
        torch.manual_seed(cfg.seed)  # same fresh heads on every rank
        grid = source.config.grid
        model = PairVPR(replace(source.config, with_stage1_head=False, dec_pos_grid=grid))
        kept = {k: v for k, v in source.state_dict().items() if not k.startswith(STAGE2_NEW)}
        # Stage one's table is the sine-cosine table of its own grid (16x16 at 224 px): stretch
        # it to this grid, as the released checkpoints hold it (23x23 at 322 px).
        kept["dec_pos_embed_cls"], kept["dec_pos_embed"] = source.dec_positions(grid * grid)
        model.load_state_dict(kept, strict=False)
        model.weights_id = source.weights_id
        return model.to(ctx.device)

    def optimizer(self, model: PairVPR) -> torch.optim.Optimizer:
        return torch.optim.AdamW(param_groups(model, self.cfg.weight_decay), lr=self.cfg.lr)

    def lr_factor(self, step: int, total: int) -> float:
        return linear_decay(step, total, self.cfg.end_lr_factor, self.cfg.warmup_steps)

    def objective(self, model: PairVPR, ctx: DistContext) -> nn.Module:
        return Stage2Objective(model, self.cfg, ctx)

    def make_step(self, objective: nn.Module, model: PairVPR, ctx: DistContext) -> StepFn:
        def step(batch: tuple[Tensor, ...]) -> dict[str, Tensor]:
            images, labels, conds = (t.to(ctx.device, non_blocking=True) for t in batch)
            return objective(images.flatten(0, 1), labels.flatten(), conds.flatten())

        return step

    def after_epoch(self, model: PairVPR) -> Callable[[int], dict] | None:
        c = self.cfg
        return (lambda epoch: validate(model, c.val, c.val_rerank_k, c.workers)) if c.val else None

    def every_steps(self, model: PairVPR) -> tuple[int, Callable[[int], dict]] | None:
        return heldout_hook(model, self.cfg.heldout, self.cfg.eval_every, self.cfg.out_dir)


def train_stage2(cfg: Stage2Config) -> Path:
    """Train stage two; returns the final weights ``<out>/stage2_final.pt`` (``load_pairvpr``)."""
    return train(Stage2(cfg))


def build_parser() -> argparse.ArgumentParser:
    return stage_parser(
        Stage2Config,
        prog="pairvpr-train-stage2",
        description="Pair-VPR stage two: global descriptor (multi-similarity) + pair classifier "
        "(batch-hard BCE). Multi-GPU: "
        "torchrun --nproc_per_node N -m pair_vpr_ros.learn.train.stage2",
    )


def main(argv: list[str] | None = None) -> int:
    return stage_main(Stage2, build_parser(), argv)


if __name__ == "__main__":
    raise SystemExit(main())
