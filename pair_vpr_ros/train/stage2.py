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

Two options beyond the paper, for training from a random init (the demo model): a linear lr
warm-up, and ``pair_weight=0``, which trains the global descriptor alone without running the
decoder (an encoder pre-training that can stand in for DINOv2 when no DINOv2 of that size exists).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor, nn
from torch.nn.parallel import DistributedDataParallel

from pair_vpr_ros.datasets import concat_collections, load_eval_set, load_places
from pair_vpr_ros.errors import ConfigError, TrainingError
from pair_vpr_ros.model import (
    ModelConfig,
    PairVPR,
    build_pairvpr,
    load_dinov2_encoder,
    load_pairvpr,
    save_pairvpr,
)
from pair_vpr_ros.model.checkpoint import STAGE2_NEW
from pair_vpr_ros.train.cli import add_common_args, common_config, run
from pair_vpr_ros.train.common import (
    DistContext,
    gather_batch,
    init_distributed,
    linear_decay,
    load_optimizer,
    param_groups,
    plain_config,
    read_training_state,
    set_trainable,
    shutdown_distributed,
)
from pair_vpr_ros.train.data import (
    AugmentConfig,
    PlaceBatchSampler,
    PlaceImagesDataset,
    make_loader,
)
from pair_vpr_ros.train.loop import LoopSettings, Progress, run_loop
from pair_vpr_ros.train.losses import MultiSimilarityObjective, batch_hard_indices, pair_bce


@dataclass
class Stage2Config:
    """Stage-two settings; defaults are the paper's where it gives them."""

    data: list[str]  # "KIND:ROOT" place collections, normally "gsv:ROOT"
    out_dir: Path
    init: Path | None = None  # stage-one (or any Pair-VPR) checkpoint; None: random init
    dinov2: Path | None = None  # with init=None: DINOv2 encoder weights
    arch: str = "B"  # used only without init/resume
    image_size: int = 322
    train_blocks: int | None = None  # last N encoder blocks train; None: half the depth
    epochs: int = 10
    max_steps: int | None = None
    places_per_batch: int = 30  # on each process
    images_per_place: int = 4
    lr: float = 8e-5
    end_lr_factor: float = 0.2
    warmup_steps: int = 0  # linear warm-up before the decay (the paper uses none)
    weight_decay: float = 0.05
    pair_weight: float = 2.0
    pair_directions: str = "both"  # "both" or "first" (see the module docstring)
    ms_alpha: float = 1.0
    ms_beta: float = 50.0
    ms_base: float = 0.0
    miner_epsilon: float = 0.1
    grad_clip: float = 1.0
    val: tuple[Path, ...] = ()  # evaluation sets (pair_vpr_ros.datasets.load_eval_set)
    val_rerank_k: int = 0  # also report re-ranked recall on validation when > 0
    workers: int = 4
    device: str = "auto"
    amp: bool = True
    augment: bool = True
    seed: int = 0
    save_every: int = 1000
    checkpoint_every: int = 1
    log_every: int = 10
    resume: Path | None = None


class Stage2Objective(nn.Module):
    """(images [B,3,S,S], labels [B]) -> {"loss", "global", "pair", "mined"} over the global
    batch. Lives inside DDP so every collective and parameter use happens in one forward."""

    def __init__(self, model: PairVPR, cfg: Stage2Config, ctx: DistContext) -> None:
        super().__init__()
        self.model, self.ctx = model, ctx
        self.pair_weight, self.both = cfg.pair_weight, cfg.pair_directions == "both"
        self.metric = MultiSimilarityObjective(
            cfg.ms_alpha, cfg.ms_beta, cfg.ms_base, cfg.miner_epsilon
        )

    def forward(self, images: Tensor, labels: Tensor) -> dict[str, Tensor]:
        dense, desc = self.model.encode(images)
        desc_all = gather_batch(desc.float(), self.ctx)
        labels_all = gather_batch(labels, self.ctx)
        with torch.autocast(desc.device.type, enabled=False):  # beta=50 needs float32
            global_loss, mined = self.metric(desc_all, labels_all)
        if self.pair_weight == 0:  # global descriptor only: the decoder is frozen and not run
            return {
                "loss": global_loss,
                "global": global_loss.detach(),
                "pair": global_loss.new_zeros(()),
                "mined": torch.tensor(float(mined)),
            }
        own = self.ctx.rank * labels.shape[0] + torch.arange(labels.shape[0], device=labels.device)
        with torch.no_grad():
            sim = desc.detach().float() @ desc_all.detach().T
            pos, neg, valid = batch_hard_indices(sim, labels, labels_all, own)
        dense_all = gather_batch(dense, self.ctx)
        anchor, positive, negative = dense[valid], dense_all[pos[valid]], dense_all[neg[valid]]
        if self.both:
            first = torch.cat([anchor, anchor, positive, negative])
            second = torch.cat([positive, negative, anchor, anchor])
        else:
            first, second = torch.cat([anchor, anchor]), torch.cat([positive, negative])
        # Rows: (anchor, positive), (anchor, negative)[, (positive, anchor), (negative, anchor)].
        logits = self.model.pair_logits(first, second).view(-1, anchor.shape[0])
        pos_logits, neg_logits = logits[0::2].flatten(), logits[1::2].flatten()
        pair_loss = pair_bce(pos_logits, neg_logits)
        return {
            "loss": global_loss + self.pair_weight * pair_loss,
            "global": global_loss.detach(),
            "pair": pair_loss.detach(),
            "mined": torch.tensor(float(mined)),
        }


def _build_model(cfg: Stage2Config, ctx: DistContext) -> tuple[PairVPR, dict | None]:
    """Resume > init checkpoint > random (+ DINOv2) init. A stage-one init gets fresh stage-two
    heads: `decoder_clstoken` ~ N(0, 1e-6), new `globalizer` and `classvprmodule`."""
    if cfg.resume is not None:
        state = read_training_state(cfg.resume)
        if state["stage"] != 2:
            raise TrainingError(
                f"{cfg.resume} is a stage-{state['stage']} checkpoint, not stage 2"
            )
        return load_pairvpr(cfg.resume, device=ctx.device), state
    if cfg.init is None:
        mcfg = ModelConfig.preset(cfg.arch, image_size=cfg.image_size)
        model = build_pairvpr(mcfg, seed=cfg.seed)
        if cfg.dinov2 is not None:
            missing = load_dinov2_encoder(model, cfg.dinov2)
            if missing and ctx.is_main:
                print(f"note: {cfg.dinov2} lacks {missing}; they keep their random init")
        return model.to(ctx.device), None
    source = load_pairvpr(
        cfg.init, image_size=cfg.image_size, allow_missing=STAGE2_NEW, with_stage1_head=True
    )
    if not source.config.with_stage1_head:  # a stage-two or released model: fine-tune it
        return source.to(ctx.device), None
    torch.manual_seed(cfg.seed)  # same fresh heads on every rank
    model = PairVPR(replace(source.config, with_stage1_head=False))
    kept = {k: v for k, v in source.state_dict().items() if not k.startswith(STAGE2_NEW)}
    model.load_state_dict(kept, strict=False)
    model.weights_id = source.weights_id
    return model.to(ctx.device), None


def validate(model: PairVPR, cfg: Stage2Config) -> dict[str, dict[str, float]]:
    """Recall@1/5/10 on each validation set (global, and re-ranked if val_rerank_k > 0)."""
    from pair_vpr_ros.evaluate import EvalConfig, evaluate_set

    ecfg = EvalConfig(
        datasets=list(cfg.val),
        rerank_k=cfg.val_rerank_k,
        recall_ns=(1, 5, 10),
        batch_size=32,
        workers=cfg.workers,
        progress=False,
    )
    out = {}
    for root in cfg.val:
        r = evaluate_set(model, load_eval_set(root), ecfg)
        out[r.dataset] = {f"R@{n}": v for n, v in r.recall_global.items()}
        out[r.dataset].update({f"rerank R@{n}": v for n, v in r.recall_rerank.items()})
    model.train()
    return out


def train_stage2(cfg: Stage2Config) -> Path:
    """Train stage two; returns the final weights ``<out>/stage2_final.pt`` (``load_pairvpr``)."""
    if cfg.pair_directions not in ("both", "first"):
        raise ConfigError(
            f"pair_directions must be 'both' or 'first', got {cfg.pair_directions!r}"
        )
    if cfg.pair_weight < 0:
        raise ConfigError(f"pair_weight must be >= 0, got {cfg.pair_weight}")
    if cfg.warmup_steps < 0:
        raise ConfigError(f"warmup_steps must be >= 0, got {cfg.warmup_steps}")
    if cfg.images_per_place < 2:
        raise ConfigError("images_per_place must be >= 2 (positives come from the same place)")
    if cfg.resume is None:  # a bad size or preset fails now, before datasets are scanned
        ModelConfig.preset(cfg.arch, image_size=cfg.image_size)
    ctx = init_distributed(cfg.device)
    try:
        if cfg.places_per_batch * ctx.world_size < 2:
            raise ConfigError(
                "a global batch needs >= 2 places (negatives): raise --places-per-batch"
            )
        return _train(cfg, ctx)
    finally:
        shutdown_distributed(ctx)


def _train(cfg: Stage2Config, ctx: DistContext) -> Path:
    places = concat_collections([load_places(spec) for spec in cfg.data])
    for root in cfg.val:  # fail before training, not after the first epoch
        load_eval_set(root)
    model, state = _build_model(cfg, ctx)
    # pair_weight 0: the decoder never runs, so it stays frozen (DDP must not wait for it)
    blocks = cfg.train_blocks or max(1, model.config.depth // 2)
    set_trainable(model, 2, blocks, decoder=cfg.pair_weight > 0)
    optimizer = torch.optim.AdamW(param_groups(model, cfg.weight_decay), lr=cfg.lr)
    progress = Progress()
    if state is not None:
        load_optimizer(optimizer, state, cfg.resume)
        progress = Progress(int(state["epoch"]), int(state["batch"]), int(state["step"]))
    augment = AugmentConfig() if cfg.augment else None
    dataset = PlaceImagesDataset(
        places, cfg.images_per_place, model.config.image_size, augment, seed=cfg.seed
    )
    sampler = PlaceBatchSampler(
        len(dataset), cfg.places_per_batch, ctx.rank, ctx.world_size, cfg.seed
    )
    loader = make_loader(dataset, sampler, cfg.workers, ctx.device.type == "cuda")
    objective: nn.Module = Stage2Objective(model, cfg, ctx)
    if ctx.distributed:
        ids = [ctx.device.index] if ctx.device.type == "cuda" else None
        objective = DistributedDataParallel(objective, device_ids=ids)
    total = cfg.max_steps or cfg.epochs * len(sampler)

    def step(batch: tuple[Tensor, ...]) -> dict[str, Tensor]:
        images, labels = (t.to(ctx.device, non_blocking=True) for t in batch)
        return objective(images.flatten(0, 1), labels.flatten())

    settings = LoopSettings(
        out_dir=cfg.out_dir,
        stage=2,
        epochs=cfg.epochs,
        base_lr=cfg.lr,
        lr_factor=lambda s: linear_decay(s, total, cfg.end_lr_factor, cfg.warmup_steps),
        max_steps=cfg.max_steps,
        grad_clip=cfg.grad_clip,
        amp=cfg.amp,
        save_every=cfg.save_every,
        checkpoint_every=cfg.checkpoint_every,
        log_every=cfg.log_every,
        config=plain_config(cfg),
    )
    after = (lambda epoch: validate(model, cfg)) if cfg.val else None
    run_loop(ctx, model, step, optimizer, dataset, sampler, loader, settings, progress, after)
    final = cfg.out_dir / "stage2_final.pt"
    if ctx.is_main:
        save_pairvpr(model, final, extra={"stage": 2})
    return final


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pairvpr-train-stage2",
        description="Pair-VPR stage two: global descriptor (multi-similarity) + pair classifier "
        "(batch-hard BCE). Multi-GPU: torchrun --nproc_per_node N -m pair_vpr_ros.train.stage2",
    )
    add_common_args(parser, image_size=322, epochs=10, places=30)
    add = parser.add_argument
    add(
        "--init",
        type=Path,
        default=None,
        help="stage-one checkpoint (stage1_final.pt) or any Pair-VPR weights to start from",
    )
    add("--images-per-place", type=int, default=4, help="images of each place per batch (4)")
    add("--lr", type=float, default=8e-5, help="initial learning rate (default 8e-5)")
    add(
        "--end-lr-factor",
        type=float,
        default=0.2,
        help="the lr falls linearly to this fraction of --lr at the end (default 0.2)",
    )
    add(
        "--warmup-steps",
        type=int,
        default=0,
        help="raise the lr linearly from 0 over this many steps first (default 0, as the paper); "
        "from a random init a warm-up keeps the global descriptor from collapsing early",
    )
    add(
        "--pair-weight",
        type=float,
        default=2.0,
        help="weight of the pair loss (default 2.0); 0 trains the global descriptor alone, "
        "without running the decoder",
    )
    add(
        "--pair-directions",
        choices=("both", "first"),
        default="both",
        help="train the pair logits in both image orders (default) or anchor-first only",
    )
    add(
        "--val",
        type=Path,
        action="append",
        default=[],
        help="validation set root (database/ + queries/), repeatable; Recall@N each epoch",
    )
    add(
        "--val-rerank-k",
        type=int,
        default=0,
        help="also report re-ranked validation recall with this K (default 0: global only)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    cfg = Stage2Config(
        **common_config(args),
        init=args.init,
        images_per_place=args.images_per_place,
        lr=args.lr,
        end_lr_factor=args.end_lr_factor,
        warmup_steps=args.warmup_steps,
        pair_weight=args.pair_weight,
        pair_directions=args.pair_directions,
        val=tuple(args.val),
        val_rerank_k=args.val_rerank_k,
    )
    return run(lambda: train_stage2(cfg))


if __name__ == "__main__":
    raise SystemExit(main())
