"""Shared training machinery: process groups, freezing, AdamW groups with layer-wise lr decay,
schedules, checkpoints and the JSON-lines log.

Runs as one plain process or under ``torchrun`` (env RANK / WORLD_SIZE / LOCAL_RANK), with NCCL on
GPUs and gloo on CPU, any number of processes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import re
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor, nn

from pair_vpr_ros.errors import CheckpointError, ConfigError, TrainingError
from pair_vpr_ros.model import save_pairvpr
from pair_vpr_ros.model.devices import check_device

_BLOCK = re.compile(r"encoder\.model\.blocks\.(\d+)\.")
_DEC_BLOCK = re.compile(r"dec_blocks\.(\d+)\.")
_EMBED = ("patch_embed.", "cls_token", "register_tokens", "pos_embed", "mask_token")


@dataclass
class DistContext:
    """Where this process sits: ``rank`` of ``world_size`` on ``device``."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")
    gather_group: object | None = None  # separate group so feature gathers never interleave DDP's

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def init_distributed(device: str = "auto") -> DistContext:
    """Join the torchrun process group if WORLD_SIZE > 1, else a single-process context."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank, local = int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))
    dev = check_device(device, local)
    if world == 1:
        return DistContext(device=dev)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    if not dist.is_initialized():
        # Long timeout: the other ranks wait at a barrier while rank 0 runs validation.
        backend = "nccl" if dev.type == "cuda" else "gloo"
        dist.init_process_group(backend=backend, timeout=timedelta(minutes=60))
    return DistContext(rank, world, local, dev, dist.new_group())


def shutdown_distributed(ctx: DistContext) -> None:
    if ctx.distributed and dist.is_initialized():
        dist.destroy_process_group()


def barrier(ctx: DistContext) -> None:
    if ctx.distributed:
        dist.barrier()


class _GatherWithGrad(torch.autograd.Function):
    """all_gather whose backward sums every rank's gradient and returns this rank's slice."""

    @staticmethod
    def forward(ctx, x: Tensor, group, world: int, rank: int) -> Tensor:  # noqa: ANN001
        parts = [torch.empty_like(x) for _ in range(world)]
        dist.all_gather(parts, x.contiguous(), group=group)
        ctx.group, ctx.rank, ctx.n = group, rank, x.shape[0]
        return torch.cat(parts)

    @staticmethod
    def backward(ctx, grad: Tensor):  # noqa: ANN001, ANN205
        grad = grad.contiguous()
        dist.all_reduce(grad, group=ctx.group)
        return grad[ctx.rank * ctx.n : (ctx.rank + 1) * ctx.n], None, None, None


def gather_batch(x: Tensor, ctx: DistContext) -> Tensor:
    """[B,...] on each rank -> [world*B,...] in rank order; gradients reach every rank's part.

    With the loss L_r of rank r, each rank's slice receives sum_r dL_r/dx; DDP then averages the
    parameter gradients, so a loss computed identically on every rank gets its exact gradient.
    Needs equal B on all ranks (the samplers drop incomplete batches)."""
    if not ctx.distributed:
        return x
    if x.requires_grad:
        return _GatherWithGrad.apply(x, ctx.gather_group, ctx.world_size, ctx.rank)
    parts = [torch.empty_like(x) for _ in range(ctx.world_size)]
    dist.all_gather(parts, x.contiguous(), group=ctx.gather_group)
    return torch.cat(parts)


def mean_over_ranks(value: float, ctx: DistContext) -> float:
    """Average of a scalar over ranks (for logging)."""
    if not ctx.distributed:
        return value
    t = torch.tensor([value], dtype=torch.float64, device=ctx.device)
    dist.all_reduce(t)
    return float(t.item()) / ctx.world_size


def set_trainable(
    model: nn.Module, stage: int, train_blocks: int, decoder: bool = True
) -> list[str]:
    """Freeze all but what ``stage`` trains; returns the trainable parameter names.

    Both stages: the last ``train_blocks`` encoder blocks (all of them also free the embeddings)
    and the encoder's final norm. Stage one adds the decoder without its class token and
    `prediction_head` (the encoder's mask token stays fixed, as the authors train: with it frozen
    nothing before the first trained block needs gradients, so autograd keeps no state there);
    stage two the decoder with its class token, `globalizer`
    and `classvprmodule`; stage two with ``decoder=False`` (global descriptor only) adds just
    `globalizer`. Parameters a stage never uses stay frozen so DDP sees no unused ones."""
    depth = model.config.depth
    if not 0 < train_blocks <= depth:
        raise ConfigError(f"train_blocks={train_blocks} must be in 1..{depth} (encoder depth)")
    first = depth - train_blocks
    dec = ("decoder_embed.", "dec_blocks.", "dec_norm.")
    if stage == 1:
        heads = (*dec, "prediction_head.")
    elif decoder:
        heads = (*dec, "decoder_clstoken", "globalizer.", "classvprmodule.")
    else:
        heads = ("globalizer.",)
    names = []
    for name, param in model.named_parameters():
        block = _BLOCK.match(name)
        if block:
            train = int(block.group(1)) >= first
        elif name.startswith("encoder.model."):
            rest = name[len("encoder.model.") :]
            train = rest.startswith("norm.") or (first == 0 and rest.startswith(_EMBED[:4]))
        else:
            train = name.startswith(heads)
        param.requires_grad_(train)
        if train:
            names.append(name)
    return names


def layer_id(name: str, depth: int, dec_depth: int = 0) -> int:
    """0 for the encoder embeddings, i+1 for encoder block i, then (``dec_depth`` > 0: the
    decoder counts as layers too) depth+1+j for decoder block j (`decoder_embed` with block 0),
    and ``depth + dec_depth + 1`` for everything after (heads, final norms)."""
    block = _BLOCK.match(name)
    if block:
        return int(block.group(1)) + 1
    if name.startswith("encoder.model.") and name[len("encoder.model.") :].startswith(_EMBED):
        return 0
    if dec_depth:
        dec = _DEC_BLOCK.match(name)
        if dec:
            return depth + 1 + int(dec.group(1))
        if name.startswith("decoder_embed."):
            return depth + 1
    return depth + dec_depth + 1


def param_groups(
    model: nn.Module, weight_decay: float, layer_decay: float = 1.0, with_decoder: bool = False
) -> list[dict[str, object]]:
    """AdamW groups of the trainable parameters; lr_scale = layer_decay ** (L + 1 - layer id)
    with L the encoder depth, or encoder + decoder depth with ``with_decoder`` (the authors'
    stage one: 0.9 over 24 layers for ViT-B).

    Biases, norms, tokens and position tables get no weight decay (``wd_scale`` 0, so a weight
    decay schedule (`apply_weight_decay`) leaves them at 0)."""
    depth = model.config.depth
    dec_depth = model.config.dec_depth if with_decoder else 0
    top = depth + dec_depth + 1
    groups: dict[tuple[int, bool], dict[str, object]] = {}
    for name, param in model.named_parameters():
        if not param.requires_grad:
            continue
        lid = layer_id(name, depth, dec_depth)
        no_decay = param.ndim <= 1 or name.endswith(("token", "tokens", "pos_embed"))
        key = (lid, no_decay)
        if key not in groups:
            groups[key] = {
                "params": [],
                "weight_decay": 0.0 if no_decay else weight_decay,
                "wd_scale": 0.0 if no_decay else 1.0,
                "lr_scale": layer_decay ** (top - lid),
            }
        groups[key]["params"].append(param)
    return [groups[k] for k in sorted(groups)]


def apply_weight_decay(optimizer: torch.optim.Optimizer, value: float) -> None:
    """Set every decayed group's weight decay to ``value`` (groups of `param_groups`)."""
    for group in optimizer.param_groups:
        group["weight_decay"] = value * group.get("wd_scale", 1.0)


def cosine(step: int, total: int, start: float, end: float) -> float:
    """``start`` at step 0 following half a cosine to ``end`` at ``total``."""
    progress = min(1.0, step / max(1, total))
    return end + (start - end) * 0.5 * (1.0 + math.cos(math.pi * progress))


def warmup_cosine(step: int, total: int, warmup: int, min_factor: float = 0.0) -> float:
    """lr factor: linear 0->1 over ``warmup`` steps, then cosine 1->``min_factor`` at ``total``."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_factor + (1.0 - min_factor) * 0.5 * (1.0 + math.cos(math.pi * progress))


def linear_decay(step: int, total: int, end_factor: float, warmup: int = 0) -> float:
    """lr factor: linear 0->1 over ``warmup`` steps, then 1 falling linearly to ``end_factor``
    at ``total``."""
    if step < warmup:
        return (step + 1) / warmup
    return 1.0 + (end_factor - 1.0) * min(1.0, (step - warmup) / max(1, total - warmup))


def apply_lr(optimizer: torch.optim.Optimizer, base_lr: float, factor: float) -> float:
    """Set every group's lr to base * factor * lr_scale; returns base * factor."""
    for group in optimizer.param_groups:
        group["lr"] = base_lr * factor * group.get("lr_scale", 1.0)
    return base_lr * factor


def autocast(device: torch.device, enabled: bool) -> contextlib.AbstractContextManager:
    """bf16 autocast on CUDA when enabled; a no-op on CPU (bf16 matmuls there are slow)."""
    if enabled and device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def unwrap(model: nn.Module) -> nn.Module:
    return model.module if hasattr(model, "module") else model


class JsonlLog:
    """Append-only JSON-lines training log (one object per line); a no-op off the main rank."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)

    def write(self, **record: object) -> None:
        if self.path is None:
            return
        with self.path.open("a", encoding="utf-8") as fh:
            fh.write(json.dumps(record) + "\n")


def plain_config(cfg: object) -> dict[str, object]:
    """A config dataclass as plain types (paths -> str, tuples -> lists) so that checkpoints
    holding it still load with ``weights_only=True``."""

    def plain(v: object) -> object:
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, list | tuple):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {str(k): plain(x) for k, x in v.items()}
        return v

    return {f.name: plain(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}


def save_training_checkpoint(
    model: nn.Module, path: Path, optimizer: torch.optim.Optimizer, state: dict[str, object]
) -> Path:
    """Weights + architecture (``save_pairvpr``, so ``load_pairvpr`` reads it) + optimizer and
    progress (``state``: epoch, step, stage, config) for ``--resume``."""
    return save_pairvpr(unwrap(model), path, extra={"optimizer": optimizer.state_dict(), **state})


def read_training_state(path: Path) -> dict[str, object]:
    """The optimizer state and progress stored by ``save_training_checkpoint``."""
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for truncated or foreign files
        raise CheckpointError(f"cannot read training checkpoint {path}: {err}") from err
    keys = obj if isinstance(obj, dict) else {}
    missing = [k for k in ("optimizer", "epoch", "step", "stage") if k not in keys]
    if missing:
        raise CheckpointError(
            f"{path} is not a training checkpoint of ours (missing {missing}): resume from the "
            "last.pt or epoch_*.pt a trainer wrote"
        )
    return obj


def load_optimizer(optimizer: torch.optim.Optimizer, state: dict, path: Path | None) -> None:
    """Restore the optimizer of a resumed run; TrainingError if its parameter groups differ."""
    try:
        optimizer.load_state_dict(state["optimizer"])
    except (ValueError, KeyError) as err:
        raise TrainingError(
            f"optimizer state in {path} does not fit this run ({err}): resume with the same "
            "--train-blocks as the original run"
        ) from err
