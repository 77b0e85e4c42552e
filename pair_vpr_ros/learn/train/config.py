"""The options both training stages share, declared once (`options` makes them flags)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pair_vpr_ros.learn.train.options import option

ARCHS = ("tiny", "small", "S", "B", "L", "G")


@dataclass
class TrainConfig:
    """Settings both stages share; each is also the flag named like it (`options`)."""

    data: list[str] = option(
        help="training places, repeatable: gsv:ROOT (GSV-Cities), folders:ROOT (one folder "
        "per place), gldv2:ROOT (Google Landmarks v2), sfxl:ROOT (SF-XL); a bare ROOT "
        "means folders",
        metavar="KIND:ROOT",
    )
    out_dir: Path = option(help="output folder for checkpoints and train_log.jsonl", flag="--out")
    arch: str = option(
        "B",
        "model size preset (S/B/L/G: the paper's encoders; small/tiny: CPU-sized)",
        choices=ARCHS,
    )
    image_size: int = option(
        322, "training image size in pixels, a multiple of 14 (default %(default)s)"
    )
    dinov2: Path | None = option(
        None, "DINOv2 *_reg4_pretrain.pth to initialise the encoder (else random init)"
    )
    train_blocks: int | None = option(
        None,
        "train only the last N encoder blocks (default: half the encoder, 6 of 12 for ViT-B)",
    )
    epochs: int = option(10, "number of epochs (default %(default)s)")
    max_steps: int | None = option(
        None, "stop after this many optimiser steps in total (default: run all epochs)"
    )
    places_per_batch: int = option(30, "places per batch on each process (default %(default)s)")
    lr: float = option(8e-5, "peak learning rate, reached after the warm-up (default %(default)s)")
    weight_decay: float = option(0.05, "AdamW weight decay (default %(default)s)")
    grad_clip: float = option(
        1.0, "clip the gradient norm to this value, 0 disables (default %(default)s)"
    )
    workers: int = option(4, "data loader worker processes (default %(default)s)")
    device: str = option(
        "auto", "auto (CUDA if available, one GPU per torchrun process), cuda or cpu"
    )
    amp: bool = option(True, "disable bf16 autocast on GPU (CPU never uses it)", flag="--no-amp")
    augment: bool = option(True, "disable crop/brightness/contrast jitter", flag="--no-augment")
    grey: float = option(
        0.0,
        "with augmentation: probability of training on a grey version of an image, so that "
        "mono8 cameras work (default %(default)s)",
    )
    grey_places: float = option(
        0.0,
        "probability that all views of a place in a batch are grey (as a mono8 camera sees "
        "it): grey places are told apart from grey places, and no place has a grey view "
        "beside a colour one (default %(default)s; jitter or not)",
    )
    exposure: float = option(
        0.0,
        "with augmentation: scale the pixel values by a gain drawn log-uniformly from "
        "[1/(1+E), 1+E] (default %(default)s: none)",
    )
    conditions: int = option(
        0,
        "the views of each place cycle through N capture conditions: view <k>.png is in "
        "condition k mod N (the demo place datasets: 3 lightings); stage two then pairs views "
        "by condition and mines positives and negatives with the same condition relation to the "
        "anchor (default %(default)s: unknown)",
    )
    seed: int = option(0, "random seed (default %(default)s)")
    save_every: int = option(
        1000, "also rewrite last.pt every N steps, 0 = only at epoch ends (default %(default)s)"
    )
    checkpoint_every: int = option(
        1, "keep epoch_NNN.pt weights every N epochs, 0 = never (default %(default)s)"
    )
    log_every: int = option(
        10, "append step, loss and lr to train_log.jsonl every N steps (default %(default)s)"
    )
    resume: Path | None = option(
        None, "continue from a last.pt written by this trainer (its architecture wins)"
    )
