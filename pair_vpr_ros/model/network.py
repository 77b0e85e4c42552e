"""`PairVPR`: encoder + global head + pair classifier, named as in the released checkpoints."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pair_vpr_ros.model.config import PATCH, ModelConfig
from pair_vpr_ros.model.decoder import PairClassifier
from pair_vpr_ros.model.encoder import Encoder
from pair_vpr_ros.model.layers import init_weights


class PairVPR(PairClassifier):
    """The full network. Top-level parameters: `encoder.model.*`, `globalizer.0`, the decoder's
    (`decoder_embed`, `dec_blocks.N`, ... see `decoder.py`) and, for stage-one training only,
    `mask_token` and `prediction_head`."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__(cfg)
        self.config = cfg
        self.encoder = Encoder(cfg)
        self.globalizer = nn.Sequential(nn.Linear(cfg.embed_dim, cfg.desc_dim))
        self.globalizer.apply(init_weights)
        if cfg.with_stage1_head:
            self.mask_token = nn.Parameter(torch.zeros(1, 1, cfg.dec_dim))
            self.prediction_head = nn.Linear(cfg.dec_dim, PATCH * PATCH * 3)
            nn.init.normal_(self.mask_token, std=0.02)
            init_weights(self.prediction_head)
        # Set by the loader: what these weights are (checkpoint hash or "random-init").
        self.weights_id = "random-init"

    @property
    def num_patches(self) -> int:
        """Dense tokens per image at the configured input size."""
        return self.config.num_patches

    @property
    def device(self) -> torch.device:
        return self.decoder_embed.weight.device

    @property
    def dense_dtype(self) -> torch.dtype:
        """The dtype `pair_scores` takes dense tokens in: the decoder's (int8 keeps it fp32)."""
        return self.decoder_embed.weight.dtype

    @property
    def fingerprint(self) -> str:
        """Identifies which descriptors this model makes: weights, input size, descriptor dim."""
        return fingerprint(self.weights_id, self.config)

    def encode(
        self, images: Tensor, fast: bool = True, pos: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Normalised images [B,3,H,W] -> (dense tokens [B,N,D], global descriptors [B,512],
        L2-normalised). `pos`: the encoder's position table for this size, precomputed."""
        feats = self.encoder.forward_features(images, fast=fast, pos=pos)
        desc = F.normalize(self.globalizer(feats["cls"]).float(), dim=-1)
        return feats["dense"], desc


def fingerprint(weights_id: str, c: ModelConfig) -> str:
    """Which descriptors a model makes: its weights (and how they run, e.g. "+int8"), input
    size, descriptor and dense sizes."""
    return f"{weights_id}|{c.arch}|{c.image_size}px|desc{c.desc_dim}|dense{c.embed_dim}"


def build_pairvpr(
    config: ModelConfig | None = None, device: str | torch.device = "cpu", seed: int | None = None
) -> PairVPR:
    """A randomly initialised network (tests, training from scratch); eval mode."""
    if seed is not None:
        torch.manual_seed(seed)
    model = PairVPR(config or ModelConfig())
    model.weights_id = f"random-init:{seed}" if seed is not None else "random-init"
    return model.to(device).eval()
