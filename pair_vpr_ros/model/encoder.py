"""DINOv2 ViT-x/14 with 4 register tokens: parameter names under `encoder.model.`.

Token order: [cls, reg0..reg3, patches row-major]; the cls token and the patches get position
embeddings (interpolated from the 37x37 grid the weights were trained at), the registers none.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.model.config import PATCH, ModelConfig
from pair_vpr_ros.model.layers import (
    LayerScale,
    Mlp,
    SelfAttention,
    SwiGLU,
    init_weights,
    layer_norm,
    tensor_version,
)

LAYERSCALE_INIT = 0.1  # for models trained from scratch here; released weights overwrite it


class Block(nn.Module):
    """Pre-norm block with LayerScale: x += ls1(attn(norm1 x)); x += ls2(mlp(norm2 x))."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        d = cfg.embed_dim
        self.norm1 = layer_norm(d)
        self.attn = SelfAttention(d, cfg.num_heads)
        self.ls1 = LayerScale(d, LAYERSCALE_INIT)
        self.norm2 = layer_norm(d)
        self.mlp = SwiGLU(d, cfg.mlp_hidden) if cfg.swiglu else Mlp(d, cfg.mlp_hidden)
        self.ls2 = LayerScale(d, LAYERSCALE_INIT)

    def forward(self, x: Tensor, fast: bool = True) -> Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), fast))
        return x + self.ls2(self.mlp(self.norm2(x)))


class PatchEmbed(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(3, dim, kernel_size=PATCH, stride=PATCH)

    def forward(self, images: Tensor) -> Tensor:
        """[B,3,H,W] -> [B, H/14 * W/14, D], row-major."""
        return self.proj(images).flatten(2).transpose(1, 2)


class DinoViT(nn.Module):
    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        d, g = cfg.embed_dim, cfg.pos_grid
        self.num_registers = cfg.num_registers
        self.patch_embed = PatchEmbed(d)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.register_tokens = nn.Parameter(torch.zeros(1, cfg.num_registers, d))
        self.mask_token = nn.Parameter(torch.zeros(1, d))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + g * g, d))
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.depth))
        self.norm = layer_norm(d)
        self._pos_cache: dict[tuple, Tensor] = {}
        self.apply(init_weights)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        nn.init.normal_(self.register_tokens, std=1e-6)

    def patch_position(self, gh: int, gw: int) -> Tensor:
        """Position embedding of the patch grid [1, gh*gw, D], bicubic + antialias in float32."""
        key = (gh, gw, tensor_version(self.pos_embed), self.pos_embed.device, self.pos_embed.dtype)
        cached = self._pos_cache.get(key)
        if cached is not None and not torch.is_grad_enabled():
            return cached
        table = self.pos_embed[:, 1:]
        side = int(round(table.shape[1] ** 0.5))
        if (gh, gw) != (side, side):
            grid = table.float().reshape(1, side, side, -1).permute(0, 3, 1, 2)
            grid = F.interpolate(grid, size=(gh, gw), mode="bicubic", antialias=True)
            table = grid.permute(0, 2, 3, 1).reshape(1, gh * gw, -1).to(self.pos_embed.dtype)
        if not torch.is_grad_enabled():
            self._pos_cache = {key: table}
        return table

    def forward_features(
        self,
        images: Tensor,
        mask: Tensor | None = None,
        fast: bool = True,
        pos: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """images [B,3,H,W] (H, W multiples of 14), mask [B,N] bool (True = masked)
        -> {"cls": [B,D], "dense": [B,N,D]}, N = (H/14)*(W/14). `pos`: `patch_position` of
        this size computed beforehand (export: for a fixed size the resize is a constant)."""
        b, _, h, w = images.shape
        if h % PATCH or w % PATCH:
            raise ConfigError(f"image size {h}x{w} is not a multiple of {PATCH} pixels")
        gh, gw = h // PATCH, w // PATCH
        x = self.patch_embed(images)
        if mask is not None:
            x = torch.where(mask.unsqueeze(-1), self.mask_token.to(x.dtype).unsqueeze(0), x)
        cls = self.cls_token.expand(b, -1, -1) + self.pos_embed[:, :1]
        x = x + (self.patch_position(gh, gw) if pos is None else pos).to(x.dtype)
        x = torch.cat([cls.to(x.dtype), self.register_tokens.expand(b, -1, -1).to(x.dtype), x], 1)
        for block in self.blocks:
            x = block(x, fast)
        x = self.norm(x)
        return {"cls": x[:, 0], "dense": x[:, 1 + self.num_registers :]}


class Encoder(nn.Module):
    """Holds the ViT as `.model`: parameter names read `encoder.model.*` as in the checkpoints."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.model = DinoViT(cfg)

    def forward_features(
        self,
        images: Tensor,
        mask: Tensor | None = None,
        fast: bool = True,
        pos: Tensor | None = None,
    ) -> dict[str, Tensor]:
        return self.model.forward_features(images, mask, fast, pos)
