"""Command-line plumbing shared by both trainers."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

from pair_vpr_ros.errors import PairVPRError

ARCHS = ("tiny", "small", "S", "B", "L", "G")


def add_common_args(
    parser: argparse.ArgumentParser, image_size: int, epochs: int, places: int
) -> None:
    """Flags both stages share (data, model size, schedule length, runtime, checkpoints)."""
    add = parser.add_argument
    add(
        "--data",
        action="append",
        required=True,
        metavar="KIND:ROOT",
        help="training places, repeatable: gsv:ROOT (GSV-Cities), folders:ROOT (one folder "
        "per place), gldv2:ROOT (Google Landmarks v2), sfxl:ROOT (SF-XL); a bare ROOT "
        "means folders",
    )
    add(
        "--out", type=Path, required=True, help="output folder for checkpoints and train_log.jsonl"
    )
    add(
        "--arch",
        default="B",
        choices=ARCHS,
        help="model size preset (S/B/L/G: the paper's encoders; small/tiny: CPU-sized)",
    )
    add(
        "--image-size",
        type=int,
        default=image_size,
        help=f"training image size in pixels, a multiple of 14 (default {image_size})",
    )
    add(
        "--dinov2",
        type=Path,
        default=None,
        help="DINOv2 *_reg4_pretrain.pth to initialise the encoder (else random init)",
    )
    add(
        "--train-blocks",
        type=int,
        default=None,
        help="train only the last N encoder blocks (default: half the encoder, 6 of 12 for ViT-B)",
    )
    add("--epochs", type=int, default=epochs, help=f"number of epochs (default {epochs})")
    add(
        "--max-steps",
        type=int,
        default=None,
        help="stop after this many optimiser steps in total (default: run all epochs)",
    )
    add(
        "--places-per-batch",
        type=int,
        default=places,
        help=f"places per batch on each process (default {places})",
    )
    add("--weight-decay", type=float, default=0.05, help="AdamW weight decay (default 0.05)")
    add(
        "--grad-clip",
        type=float,
        default=1.0,
        help="clip the gradient norm to this value, 0 disables (default 1.0)",
    )
    add("--workers", type=int, default=4, help="data loader worker processes (default 4)")
    add(
        "--device",
        default="auto",
        help="auto (CUDA if available, one GPU per torchrun process), cuda or cpu",
    )
    add("--no-amp", action="store_true", help="disable bf16 autocast on GPU (CPU never uses it)")
    add("--no-augment", action="store_true", help="disable crop/brightness/contrast jitter")
    add("--seed", type=int, default=0, help="random seed (default 0)")
    add(
        "--save-every",
        type=int,
        default=1000,
        help="also rewrite last.pt every N steps, 0 = only at epoch ends (default 1000)",
    )
    add(
        "--checkpoint-every",
        type=int,
        default=1,
        help="keep epoch_NNN.pt weights every N epochs, 0 = never (default 1)",
    )
    add(
        "--log-every",
        type=int,
        default=10,
        help="append step, loss and lr to train_log.jsonl every N steps (default 10)",
    )
    add(
        "--resume",
        type=Path,
        default=None,
        help="continue from a last.pt written by this trainer (its architecture wins)",
    )


# Config fields named like the shared flags (see `add_common_args`).
COMMON_FIELDS = (
    "arch", "image_size", "dinov2", "train_blocks", "epochs", "max_steps", "places_per_batch",
    "weight_decay", "grad_clip", "workers", "device", "seed", "save_every", "checkpoint_every",
    "log_every", "resume",
)  # fmt: skip


def common_config(args: argparse.Namespace) -> dict:
    """The config fields both stages take from the shared flags."""
    fields = {name: getattr(args, name) for name in COMMON_FIELDS}
    return {
        **fields, "data": args.data, "out_dir": args.out, "amp": not args.no_amp,
        "augment": not args.no_augment,
    }  # fmt: skip


def run(fn: Callable[[], Path]) -> int:
    """Run a trainer; user errors print ``error: ...`` and return 2, Ctrl-C returns 130."""
    try:
        path = fn()
    except PairVPRError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted; resume with --resume <out>/last.pt", file=sys.stderr)
        return 130
    if os.environ.get("RANK", "0") == "0":  # one line per run, not per torchrun process
        print(f"wrote {path}")
    return 0
