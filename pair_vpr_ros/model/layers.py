"""Transformer pieces shared by the encoder and the pair decoder.

Every attention goes through `attend`, which has two paths: the fused torch kernel
(`scaled_dot_product_attention`, used in production) and a plain softmax(QK^T/sqrt(d))V reference
that the tests compare against.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def attend(q: Tensor, k: Tensor, v: Tensor, fast: bool = True) -> Tensor:
    """Attention over heads: q [B,H,Tq,d], k/v [B,H,Tk,d] -> [B,H,Tq,d]."""
    if fast:
        return F.scaled_dot_product_attention(q, k, v)
    weights = (q @ k.transpose(-2, -1)) * q.shape[-1] ** -0.5
    return weights.softmax(dim=-1) @ v


def split_heads(x: Tensor, heads: int) -> Tensor:
    """[B,T,C] -> [B,H,T,C/H]."""
    b, t, c = x.shape
    return x.reshape(b, t, heads, c // heads).transpose(1, 2)


def merge_heads(x: Tensor) -> Tensor:
    """[B,H,T,d] -> [B,T,H*d]."""
    b, h, t, d = x.shape
    return x.transpose(1, 2).reshape(b, t, h * d)


class SelfAttention(nn.Module):
    """`qkv` is Linear(C, 3C) laid out as [q | k | v], each split into heads in order."""

    def __init__(self, dim: int, heads: int, bias: bool = True) -> None:
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=bias)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, fast: bool = True, first_row_only: bool = False) -> Tensor:
        """x [B,T,C] -> [B,T,C], or [B,1,C] for the first token alone (keys still use all T)."""
        b, t, c = x.shape
        qkv = self.qkv(x).reshape(b, t, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv.unbind(0)
        if first_row_only:
            q = q[:, :, :1]
        return self.proj(merge_heads(attend(q, k, v, fast)))


class Mlp(nn.Module):
    """fc1 -> GELU (erf) -> fc2."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class SwiGLU(nn.Module):
    """ViT-G's feed-forward: `w12` D -> 2H split into a, b; silu(a) * b; `w3` H -> D."""

    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.w12 = nn.Linear(dim, 2 * hidden)
        self.w3 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        a, b = self.w12(x).chunk(2, dim=-1)
        return self.w3(F.silu(a) * b)


class LayerScale(nn.Module):
    def __init__(self, dim: int, init: float) -> None:
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), init))

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gamma


def tensor_version(t: Tensor) -> int:
    """In-place modification counter (cache key); inference tensors have none and never change
    outside inference mode."""
    try:
        return t._version
    except RuntimeError:
        return -1


def layer_norm(dim: int) -> nn.LayerNorm:
    return nn.LayerNorm(dim, eps=1e-6)


def init_weights(module: nn.Module, xavier: bool = False) -> None:
    """Truncated-normal (std 0.02; ``xavier``: Xavier-uniform) Linear weights, zero biases, unit
    LayerNorms."""
    if isinstance(module, nn.Linear):
        if xavier:
            nn.init.xavier_uniform_(module.weight)
        else:
            nn.init.trunc_normal_(module.weight, std=0.02)
        if module.bias is not None:
            nn.init.zeros_(module.bias)
    elif isinstance(module, nn.LayerNorm):
        nn.init.ones_(module.weight)
        nn.init.zeros_(module.bias)
