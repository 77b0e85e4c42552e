"""The training driver both stages share: options, model start and resume, freezing, data,
DDP, the loop and the final weights. A stage (`Stage` subclass) adds its objective and step.

Runs as one plain process or under ``torchrun`` (one process per GPU, gloo on CPU).
"""

from __future__ import annotations

import argparse
import os
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import ClassVar

import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from pair_vpr_ros.cli import run_cli
from pair_vpr_ros.errors import ConfigError, TrainingError
from pair_vpr_ros.learn.places import concat_collections, load_places
from pair_vpr_ros.learn.train.common import (
    DistContext,
    init_distributed,
    load_optimizer,
    plain_config,
    read_training_state,
    set_trainable,
    shutdown_distributed,
)
from pair_vpr_ros.learn.train.config import TrainConfig
from pair_vpr_ros.learn.train.data import place_data
from pair_vpr_ros.learn.train.loop import LoopJob, LoopSettings, Progress, StepFn, run_loop
from pair_vpr_ros.learn.train.options import add_options, config_from_args
from pair_vpr_ros.model import (
    ModelConfig,
    PairVPR,
    build_pairvpr,
    load_dinov2_encoder,
    load_pairvpr,
    save_pairvpr,
)


def stage_parser(cls: type[TrainConfig], prog: str, description: str) -> argparse.ArgumentParser:
    """The command line of one stage: a flag for each option of its config class."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    add_options(parser, cls)
    return parser


def stage_main(stage: type[Stage], parser: argparse.ArgumentParser, argv: list[str] | None) -> int:
    """A trainer's command line: parse, train, print the final weights' path (once, not per
    torchrun process). Exit codes: ``pair_vpr_ros.cli``."""

    def body(args: argparse.Namespace) -> None:
        path = train(stage(config_from_args(stage.config_class, args)))
        if os.environ.get("RANK", "0") == "0":
            print(f"wrote {path}")

    resume = "interrupted; resume with --resume <out>/last.pt"
    return run_cli(parser, body, argv, interrupted=resume)


class Stage(ABC):
    """What one stage adds to the driver: its number, batch shape, optimizer, schedule,
    objective and step. The other hooks are behaviour both stages share."""

    number: ClassVar[int]
    config_class: ClassVar[type[TrainConfig]]
    with_stage1_head: ClassVar[bool] = False  # the model carries stage one's prediction head

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg

    @property
    @abstractmethod
    def images_per_place(self) -> int:
        """k of the P places x k images batches."""

    @property
    def trains_decoder(self) -> bool:
        return True

    @property
    def pair_conditions(self) -> bool:
        """Batches of view pairs that share a capture condition (see `data`)."""
        return False

    def check(self) -> None:
        """Config errors found before any process group, dataset or model exists."""
        for name in ("grey", "grey_places"):
            value = getattr(self.cfg, name)
            if not 0.0 <= value <= 1.0:  # also NaN
                raise ConfigError(f"{name}={value}: a probability, use a value in 0..1")
        if self.cfg.conditions < 0:
            raise ConfigError(f"conditions={self.cfg.conditions}: must be >= 0 (0 = unknown)")
        if not self.cfg.exposure >= 0:
            raise ConfigError(f"exposure={self.cfg.exposure}: must be >= 0 (0 = no gain jitter)")
        if self.cfg.resume is None:  # a bad size or preset fails now, before datasets are scanned
            ModelConfig.preset(self.cfg.arch, image_size=self.cfg.image_size)

    def prepare(self, ctx: DistContext) -> None:  # noqa: B027 (a hook stage two uses)
        """Checks that need the process group, before the training places are scanned."""

    def model_config(self) -> ModelConfig:
        """The network a run that does not resume starts from (a stage may adjust it)."""
        cfg = self.cfg
        return ModelConfig.preset(
            cfg.arch, image_size=cfg.image_size, with_stage1_head=self.with_stage1_head
        )

    def start_model(self, ctx: DistContext) -> PairVPR:
        """The model of a run that does not resume: random init, same on every rank, with the
        DINOv2 encoder weights when given."""
        cfg = self.cfg
        model = build_pairvpr(self.model_config(), seed=cfg.seed)
        if cfg.dinov2 is not None:
            missing = load_dinov2_encoder(model, cfg.dinov2)
            if missing and ctx.is_main:
                print(f"note: {cfg.dinov2} lacks {missing}; they keep their random init")
        return model.to(ctx.device)

    def resume_model(self, ctx: DistContext) -> tuple[PairVPR, dict]:
        """The model and training state stored in ``cfg.resume`` by this stage."""
        path = self.cfg.resume
        state = read_training_state(path)
        if state["stage"] != self.number:
            raise TrainingError(
                f"{path} is a stage-{state['stage']} checkpoint, not stage {self.number}"
            )
        model = load_pairvpr(path, device=ctx.device, with_stage1_head=self.with_stage1_head)
        if self.with_stage1_head and not model.config.with_stage1_head:
            raise TrainingError(f"{path} has no prediction_head: not a stage-one checkpoint")
        return model, state

    @abstractmethod
    def optimizer(self, model: PairVPR) -> torch.optim.Optimizer:
        """AdamW over the trainable parameters (after `set_trainable`)."""

    @abstractmethod
    def lr_factor(self, step: int, total: int) -> float:
        """Multiplier of ``cfg.lr`` at ``step`` of ``total``."""

    @abstractmethod
    def objective(self, model: PairVPR, ctx: DistContext) -> nn.Module:
        """The module DDP wraps: every forward computation and collective of a step."""

    @abstractmethod
    def make_step(self, objective: nn.Module, model: PairVPR, ctx: DistContext) -> StepFn:
        """batch -> {"loss": scalar, other logged terms}."""

    def after_epoch(self, model: PairVPR) -> Callable[[int], dict] | None:
        """epoch -> metrics to log (main rank only), or None."""
        return None

    def every_steps(self, model: PairVPR) -> tuple[int, Callable[[int], dict]] | None:
        """(N, step -> metrics) to log every N steps (main rank only), or None."""
        return None

    def base_lr(self, ctx: DistContext) -> float:
        """The peak learning rate (``cfg.lr``; stage one may derive it from the batch)."""
        return self.cfg.lr

    def weight_decay_at(self, step: int, total: int) -> float | None:
        """AdamW weight decay at ``step``, or None to keep ``cfg.weight_decay`` throughout."""
        return None


def train(stage: Stage) -> Path:
    """Train ``stage``; returns its final weights ``<out>/stage<N>_final.pt``."""
    stage.check()
    ctx = init_distributed(stage.cfg.device)
    try:
        return _train(stage, ctx)
    finally:
        shutdown_distributed(ctx)


def _train(stage: Stage, ctx: DistContext) -> Path:
    cfg = stage.cfg
    stage.prepare(ctx)
    places = concat_collections([load_places(spec) for spec in cfg.data])
    if cfg.resume is not None:
        model, state = stage.resume_model(ctx)
    else:
        model, state = stage.start_model(ctx), None
    blocks = cfg.train_blocks or max(1, model.config.depth // 2)
    set_trainable(model, stage.number, blocks, decoder=stage.trains_decoder)
    optimizer = stage.optimizer(model)
    progress = Progress()
    if state is not None:
        load_optimizer(optimizer, state, cfg.resume)
        progress = Progress(int(state["epoch"]), int(state["batch"]), int(state["step"]))
    data = place_data(
        places, stage.images_per_place, model.config.image_size, cfg, ctx, stage.pair_conditions
    )
    objective = stage.objective(model, ctx)
    if ctx.distributed:
        ids = [ctx.device.index] if ctx.device.type == "cuda" else None
        objective = DistributedDataParallel(objective, device_ids=ids)
    total = cfg.max_steps or cfg.epochs * len(data.sampler)
    every = stage.every_steps(model)  # every rank: they meet at a barrier after it
    settings = LoopSettings(
        out_dir=cfg.out_dir,
        stage=stage.number,
        epochs=cfg.epochs,
        base_lr=stage.base_lr(ctx),
        lr_factor=lambda step: stage.lr_factor(step, total),
        max_steps=cfg.max_steps,
        grad_clip=cfg.grad_clip,
        amp=cfg.amp,
        save_every=cfg.save_every,
        checkpoint_every=cfg.checkpoint_every,
        log_every=cfg.log_every,
        config=plain_config(cfg),
        weight_decay=(
            (lambda step: stage.weight_decay_at(step, total))
            if stage.weight_decay_at(0, total) is not None
            else None
        ),
        eval_every=every[0] if every else 0,
    )
    step = stage.make_step(objective, model, ctx)
    job = LoopJob(
        ctx,
        model,
        optimizer,
        step,
        data,
        settings,
        stage.after_epoch(model),
        every[1] if every else None,
    )
    run_loop(job, progress)
    final = cfg.out_dir / f"stage{stage.number}_final.pt"
    if ctx.is_main:
        save_pairvpr(model, final, extra={"stage": stage.number})
    return final
