"""The epoch/step loop both stages share: lr schedule, AMP, clipping, logging, checkpoints."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor, nn
from tqdm import tqdm

from pair_vpr_ros.errors import TrainingError
from pair_vpr_ros.learn.train.common import (
    DistContext,
    JsonlLog,
    apply_lr,
    apply_weight_decay,
    autocast,
    barrier,
    mean_over_ranks,
    save_training_checkpoint,
)
from pair_vpr_ros.learn.train.data import PlaceData
from pair_vpr_ros.model import save_pairvpr

StepFn = Callable[[tuple[Tensor, ...]], dict[str, Tensor]]  # batch -> {"loss": scalar, ...}


@dataclass
class Progress:
    """Where training stands; stored in last.pt so ``--resume`` continues mid-epoch."""

    epoch: int = 0
    batch: int = 0  # batches of `epoch` already done
    step: int = 0  # optimiser steps in total


@dataclass
class LoopSettings:
    out_dir: Path
    stage: int
    epochs: int
    base_lr: float
    lr_factor: Callable[[int], float]  # step -> multiplier of base_lr
    max_steps: int | None = None
    grad_clip: float = 1.0
    amp: bool = True
    save_every: int = 1000
    checkpoint_every: int = 1
    log_every: int = 10
    config: dict = field(default_factory=dict)  # stored in checkpoints (plain types only)
    weight_decay: Callable[[int], float] | None = None  # step -> weight decay (a schedule)
    eval_every: int = 0  # call LoopJob.every_steps every N steps (main rank), 0 = never


@dataclass
class LoopJob:
    """Everything `run_loop` drives: ``step(batch)`` gives the loss and the logged terms;
    ``after_epoch(epoch)`` (main rank only) gives metrics to log."""

    ctx: DistContext
    model: nn.Module
    optimizer: torch.optim.Optimizer
    step: StepFn
    data: PlaceData
    settings: LoopSettings
    after_epoch: Callable[[int], dict] | None = None
    every_steps: Callable[[int], dict] | None = None  # step -> metrics (held-out evaluation)


def _save(
    ctx: DistContext,
    model: nn.Module,
    opt,
    s: LoopSettings,
    p: Progress,
    name: str,  # noqa: ANN001
) -> None:
    """last.pt carries the optimizer for --resume; epoch snapshots are weights + progress only."""
    if not ctx.is_main:
        return
    state = {
        "stage": s.stage,
        "epoch": p.epoch,
        "batch": p.batch,
        "step": p.step,
        "config": s.config,
    }
    if name == "last.pt":
        save_training_checkpoint(model, s.out_dir / name, opt, state)
    else:
        save_pairvpr(model, s.out_dir / name, extra=state)


def run_loop(job: LoopJob, progress: Progress) -> Progress:
    """Train from ``progress`` until ``settings.epochs`` or ``settings.max_steps``."""
    ctx, model, optimizer, s = job.ctx, job.model, job.optimizer, job.settings
    dataset, sampler = job.data.dataset, job.data.sampler
    log = JsonlLog(s.out_dir / "train_log.jsonl" if ctx.is_main else None)
    if ctx.is_main:
        print(
            f"stage {s.stage}: {len(dataset)} places ({dataset.dropped_places} with fewer than "
            f"{dataset.k} images left out); per process {len(sampler)} batches of {sampler.p} "
            f"places x {dataset.k} images; {ctx.world_size} process(es) on {ctx.device.type}"
        )
    params = [p for p in model.parameters() if p.requires_grad]
    while progress.epoch < s.epochs:
        model.train()
        sampler.set_epoch(progress.epoch, progress.batch)
        dataset.set_epoch(progress.epoch)
        bar = tqdm(
            job.data.loader,
            total=len(sampler) - progress.batch,
            disable=not ctx.is_main,
            desc=f"stage {s.stage} epoch {progress.epoch}",
            dynamic_ncols=True,
        )
        for batch in bar:
            lr = apply_lr(optimizer, s.base_lr, s.lr_factor(progress.step))
            if s.weight_decay is not None:
                apply_weight_decay(optimizer, s.weight_decay(progress.step))
            with autocast(ctx.device, s.amp):
                terms = job.step(batch)
            loss = terms["loss"]
            if mean_over_ranks(float(not torch.isfinite(loss.detach())), ctx) > 0:
                raise TrainingError(
                    f"stage {s.stage} loss is not finite at step {progress.step}: lower the "
                    f"learning rate or check the data; resume from {s.out_dir / 'last.pt'}"
                )
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if s.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(params, s.grad_clip)
            optimizer.step()
            progress.step += 1
            progress.batch += 1
            if progress.step % s.log_every == 0 or progress.step == 1:
                values = {k: mean_over_ranks(float(v.detach()), ctx) for k, v in terms.items()}
                log.write(step=progress.step, epoch=progress.epoch, lr=lr, **values)
                bar.set_postfix(loss=f"{values['loss']:.4f}", lr=f"{lr:.2e}")
            if s.save_every and progress.step % s.save_every == 0:
                _save(ctx, model, optimizer, s, progress, "last.pt")
            if job.every_steps is not None and s.eval_every and progress.step % s.eval_every == 0:
                if ctx.is_main:
                    log.write(step=progress.step, heldout=job.every_steps(progress.step))
                    model.train()
                barrier(ctx)
            if s.max_steps and progress.step >= s.max_steps:
                break
        bar.close()
        if s.max_steps and progress.step >= s.max_steps and progress.batch < len(sampler):
            _save(ctx, model, optimizer, s, progress, "last.pt")
            break
        done = progress.epoch
        progress.epoch, progress.batch = done + 1, 0
        if job.after_epoch is not None:
            if ctx.is_main:
                log.write(epoch=done, step=progress.step, val=job.after_epoch(done))
            barrier(ctx)
        _save(ctx, model, optimizer, s, progress, "last.pt")
        if s.checkpoint_every and (done + 1) % s.checkpoint_every == 0:
            _save(ctx, model, optimizer, s, progress, f"epoch_{done:03d}.pt")
        if s.max_steps and progress.step >= s.max_steps:
            break
    barrier(ctx)
    return progress
