"""Stage two on drives: tune the pair classifier on what the node re-ranks (issue 24).

Stage two trains the pair classifier on discrete clusters of views of synthetic places; in the
node it re-ranks a keyframe's global top-K, mostly near-duplicate frames of one stretch of road.
This stage fine-tunes ONLY the pair classifier (decoder, its class token and `classvprmodule`;
encoder and global descriptor frozen, so the maps' dense tokens and descriptors stay valid) on
replayed drives (`drive_pairs`): each batch takes `batch` mined queries, one random positive and
one random hard negative (a global top-K candidate far away) each, scored in both orders, plus
`twins` identical pairs per batch so that an exact repeat keeps outscoring a revisit, plus
`lonely` keyframes of new ground (no true match anywhere before them) against one hard negative
each, so that a first visit scores low whatever its candidates look like; binary
cross-entropy, AdamW. Batches are drawn from a generator seeded with (seed, step), so a resumed
run takes the same batches as an uninterrupted one.

    python -m pair_vpr_ros.learn.train.pair_tune --init stage2_final.pt \\
        --drive r101/map --drive r102/map --val r201/map --out pair_tune
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from pair_vpr_ros.cli import run_cli
from pair_vpr_ros.errors import ConfigError, DatasetError, TrainingError, UsageError
from pair_vpr_ros.learn.train.common import (
    JsonlLog,
    load_optimizer,
    plain_config,
    read_training_state,
    save_training_checkpoint,
)
from pair_vpr_ros.learn.train.drive_pairs import (
    Drive,
    DriveQuery,
    MiningRule,
    load_drive,
    rerank_ap,
)
from pair_vpr_ros.learn.train.losses import pair_bce
from pair_vpr_ros.learn.train.options import add_options, config_from_args, option
from pair_vpr_ros.model import PairVPR, load_pairvpr, save_pairvpr
from pair_vpr_ros.model.devices import check_device

PAIR_CLASSIFIER = ("decoder_embed", "dec_blocks", "dec_norm", "decoder_clstoken", "classvprmodule")
STAGE = "pair_tune"
FINAL = "pair_tune_final.pt"


@dataclass
class PairTuneConfig:
    """Settings of the stage; each is also the flag named like it."""

    init: Path = option(
        help="Pair-VPR checkpoint to tune (stage two's stage2_final.pt)", metavar="CKPT"
    )
    drive: tuple[Path, ...] = option(
        help="place map of a training drive, repeatable (pairvpr-bag-replay --pose-topic "
        "<true poses> --weights <--init> --out DIR writes it to DIR/map)",
        metavar="MAPDIR",
    )
    out: Path = option(help="output folder: last.pt, train_log.jsonl, " + FINAL, metavar="DIR")
    val: Path | None = option(
        None, "place map of a validation drive: AP every --eval-every steps", metavar="MAPDIR"
    )
    top_k: int = option(10, "global candidates per keyframe, as the node (default %(default)s)")
    exclude_recent_s: float = option(
        8.0, "the detector's exclusion: seconds (default %(default)s, as config/demo.yaml)"
    )
    exclude_recent_keyframes: int = option(
        10, "the detector's exclusion: newest keyframes (default %(default)s)"
    )
    gt_radius: float = option(10.0, "a candidate this close (m) is a true match (default 10)")
    negative_radius: float = option(
        15.0, "a candidate farther (m) is a hard negative (default 15; in between: ignored)"
    )
    batch: int = option(32, "queries per step (default %(default)s)")
    twins: int = option(8, "identical pairs (q, q) per batch, as positives (default %(default)s)")
    lonely: int = option(
        0,
        "keyframes per step with no true match in the map (new ground), each against one hard "
        "negative in both orders, so that a first visit scores low (default %(default)s)",
    )
    steps: int = option(600, "optimiser steps in total (default %(default)s)")
    lr: float = option(1e-4, "AdamW learning rate (default %(default)s)")
    weight_decay: float = option(0.05, "AdamW weight decay (default %(default)s)")
    seed: int = option(0, "seed of the batch sampler (default %(default)s)")
    device: str = option(
        "cpu", "torch device: cpu, cuda, cuda:1 or auto (CUDA if there is one; default cpu)"
    )
    save_every: int = option(100, "rewrite OUT/last.pt every N steps (default %(default)s)")
    log_every: int = option(10, "log step and loss every N steps (default %(default)s)")
    eval_every: int = option(250, "with --val: measure every N steps (default %(default)s)")
    resume: Path | None = option(
        None, "continue from a last.pt this stage wrote", metavar="LAST_PT"
    )
    progress: bool = option(True, "no progress bar", flag="--no-progress")

    def __post_init__(self) -> None:
        checks = [
            ("top_k", self.top_k >= 1, "must be >= 1"),
            ("exclude_recent_s", self.exclude_recent_s >= 0, "must be >= 0"),
            ("exclude_recent_keyframes", self.exclude_recent_keyframes >= 0, "must be >= 0"),
            ("gt_radius", self.gt_radius > 0, "must be > 0 (metres)"),
            ("negative_radius", self.negative_radius >= self.gt_radius, "must be >= gt_radius"),
            ("batch", self.batch >= 1, "must be >= 1"),
            ("twins", self.twins >= 0, "must be >= 0"),
            ("lonely", self.lonely >= 0, "must be >= 0"),
            ("steps", self.steps >= 1, "must be >= 1"),
            ("lr", self.lr > 0, "must be > 0"),
            ("weight_decay", self.weight_decay >= 0, "must be >= 0"),
            ("save_every", self.save_every >= 1, "must be >= 1"),
            ("log_every", self.log_every >= 1, "must be >= 1"),
            ("eval_every", self.eval_every >= 0, "must be >= 0 (0 = never)"),
        ]
        for name, ok, need in checks:
            value = getattr(self, name)
            if not ok or (isinstance(value, float) and not math.isfinite(value)):
                raise ConfigError(f"{name}={value}: {need}")

    @property
    def rule(self) -> MiningRule:
        keys = MiningRule.__dataclass_fields__
        return MiningRule(**{k: v for k, v in asdict(self).items() if k in keys})


def freeze_all_but_pair_classifier(model: PairVPR) -> list[torch.nn.Parameter]:
    """requires_grad only on the pair classifier's parameters (returned, in model order)."""
    params = []
    for name, param in model.named_parameters():
        param.requires_grad_(name.startswith(PAIR_CLASSIFIER))
        if param.requires_grad:
            params.append(param)
    return params


def _draw(
    pools: list[list[DriveQuery]], count: int, rng: np.random.Generator, row: Callable
) -> list[tuple[int, list[tuple]]]:
    """(drive, [row(query)]) per drive: ``count`` queries drawn uniformly over all ``pools``."""
    flat = [(d, q) for d, pool in enumerate(pools) for q in pool]
    picks = [flat[i] for i in rng.integers(0, len(flat), count)]
    out = []
    for d in range(len(pools)):
        rows = [row(q) for dq, q in picks if dq == d]
        if rows:
            out.append((d, rows))
    return out


def sample_batch(
    pools: list[list[DriveQuery]], batch: int, seed: int, step: int
) -> list[tuple[int, list[tuple[int, int, int]]]]:
    """(drive, [(query, positive, negative)]) per drive drawn in step ``step``: ``batch``
    queries uniformly over all drives' trainable queries, keyed by (seed, step) alone."""
    rng = np.random.default_rng([seed, step])
    return _draw(
        pools,
        batch,
        rng,
        lambda q: (q.query, int(rng.choice(q.positives)), int(rng.choice(q.negatives))),
    )


def sample_lonely(
    pools: list[list[DriveQuery]], count: int, seed: int, step: int
) -> list[tuple[int, list[tuple[int, int]]]]:
    """(drive, [(query, negative)]) per drive: ``count`` keyframes of new ground drawn in step
    ``step``, keyed by (seed, step) on a stream of their own (``sample_batch`` draws the same
    rows whatever ``count`` is); [] when no drive has such a keyframe."""
    if not count or not any(pools):
        return []
    rng = np.random.default_rng([seed, step, 1])
    return _draw(pools, count, rng, lambda q: (q.query, int(rng.choice(q.negatives))))


def _stack(model: PairVPR, drives: list[Drive], picked: list) -> tuple[Tensor, ...]:
    """Each column of ``picked``'s rows (ids) -> the dense tokens of all drives, stacked."""
    cols = [[drives[d].dense[list(col)] for col in zip(*rows, strict=True)] for d, rows in picked]
    return tuple(torch.cat(part).to(model.device) for part in zip(*cols, strict=True))


def batch_loss(
    model: PairVPR, drives: list[Drive], picked: list, twins: int, lonely: list | None = None
) -> Tensor:
    """BCE over logit(a,b) and logit(b,a) of each (query, positive) and (query, negative),
    plus the first ``twins`` queries against themselves (q, q) as positives and each
    (query, negative) of ``lonely`` (`sample_lonely`) as negatives. All drives' rows go
    through the classifier together (one call per kind: a call per drive is ~10x slower with
    a dozen drives on a CPU)."""
    a, p, n = _stack(model, drives, picked)
    pos = [model.pair_logits(a, p), model.pair_logits(p, a)]
    neg = [model.pair_logits(a, n), model.pair_logits(n, a)]
    if twins:
        pos.append(model.pair_logits(a[:twins], a[:twins]))
    if lonely:
        la, ln = _stack(model, drives, lonely)
        neg += [model.pair_logits(la, ln), model.pair_logits(ln, la)]
    return pair_bce(torch.cat(pos), torch.cat(neg))


def _load_drives(
    paths: tuple[Path, ...], cfg: PairTuneConfig, model: PairVPR, training: bool
) -> list[Drive]:
    """Load and mine each map; DatasetError for one with nothing to train on (``training``)
    or, for validation, no query with a true match."""
    shape = (model.num_patches, model.config.embed_dim)
    drives = [load_drive(p, cfg.rule, shape, model.weights_id) for p in paths]
    for drive in drives:
        if training and not drive.trainable:
            raise DatasetError(
                f"drive map {drive.path}: no keyframe has both a positive (<= {cfg.gt_radius} "
                f"m) and a hard negative (> {cfg.negative_radius} m) among its "
                f"{cfg.top_k} global candidates: give a drive that revisits places, or check "
                "--gt-radius, --negative-radius and the exclusion flags"
            )
        if not training and not any(q.has_match for q in drive.queries):
            raise DatasetError(
                f"validation map {drive.path}: no keyframe has a true match (<= "
                f"{cfg.gt_radius} m) among its eligible keyframes: give a drive that revisits"
            )
    return drives


def pair_tune(cfg: PairTuneConfig) -> Path:
    """Run the stage; -> OUT/pair_tune_final.pt (the project's checkpoint format)."""
    if cfg.resume is None and (cfg.out / "last.pt").exists():
        raise UsageError(
            f"{cfg.out} holds a run already: pass --resume {cfg.out / 'last.pt'} or another --out"
        )
    device = check_device(cfg.device)
    torch.manual_seed(cfg.seed)
    model = load_pairvpr(cfg.init, device=device)
    drives = _load_drives(cfg.drive, cfg, model, training=True)
    val = _load_drives((cfg.val,), cfg, model, training=False) if cfg.val else []
    pools = [d.trainable for d in drives]
    lonely_pools = [d.lonely for d in drives]
    params = freeze_all_but_pair_classifier(model)
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    start = 0
    if cfg.resume is not None:
        state = read_training_state(cfg.resume)
        if state["stage"] != STAGE:
            raise TrainingError(f"{cfg.resume} was written by {state['stage']}, not {STAGE}")
        model.load_state_dict(state["model"])
        load_optimizer(opt, state, cfg.resume)
        start = int(state["step"])
    log = JsonlLog(cfg.out / "train_log.jsonl")
    if val and start == 0:
        log.write(step=0, val=rerank_ap(model, val, cfg.gt_radius))
    model.train()
    for step in tqdm(range(start + 1, cfg.steps + 1), disable=not cfg.progress, desc=STAGE):
        picked = sample_batch(pools, cfg.batch, cfg.seed, step)
        lonely = sample_lonely(lonely_pools, cfg.lonely, cfg.seed, step)
        loss = batch_loss(model, drives, picked, cfg.twins, lonely)
        if not torch.isfinite(loss):
            raise TrainingError(f"loss is {loss.item()} at step {step}: lower --lr")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % cfg.log_every == 0:
            log.write(step=step, loss=round(loss.item(), 5))
        if val and cfg.eval_every and step % cfg.eval_every == 0:
            log.write(step=step, val=rerank_ap(model, val, cfg.gt_radius))
        if step % cfg.save_every == 0 or step == cfg.steps:
            state = {"step": step, "epoch": 0, "stage": STAGE, "config": plain_config(cfg)}
            save_training_checkpoint(model, cfg.out / "last.pt", opt, state)
    return save_pairvpr(model.eval(), cfg.out / FINAL)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m pair_vpr_ros.learn.train.pair_tune",
        description="Fine-tune the pair classifier of a Pair-VPR checkpoint on replayed drives "
        "(hard negatives from each keyframe's global top-K); docs/training.md.",
    )
    add_options(p, PairTuneConfig)
    return p


def main(argv: list[str] | None = None) -> int:
    def body(args: argparse.Namespace) -> int:
        path = pair_tune(config_from_args(PairTuneConfig, args))
        print(f"wrote {path}")
        return 0

    resume = "interrupted; resume with --resume <out>/last.pt"
    return run_cli(build_parser(), body, argv, interrupted=resume)


if __name__ == "__main__":
    raise SystemExit(main())
