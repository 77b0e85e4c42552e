"""The pair classifier: a 12-block cross-attention decoder that scores whether two images show the
same place. Its parameters sit at the top level of the checkpoint (`decoder_embed`, `dec_blocks.N`,
`dec_norm`, `classvprmodule`, ...), so `PairClassifier` is a base class of `PairVPR`, not a child.

Two paths compute the same numbers:
- `pair_logits(..., fast=False)`: plain, one pair at a time, explicit attention (the reference);
- `pair_scores`: both directions of all K candidates batched; each image's decoder input computed
  once; in the reverse direction the query is every pair's cross-attention memory, so its keys and
  values are computed once per block; block 0's self-attention of the query (identical for all K)
  runs once; the last block computes only the class-token row.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .config import ModelConfig
from .layers import (
    Mlp,
    SelfAttention,
    attend,
    init_weights,
    layer_norm,
    merge_heads,
    split_heads,
    tensor_version,
)


class CrossAttention(nn.Module):
    def __init__(self, dim: int, heads: int, bias: bool = True) -> None:
        super().__init__()
        self.heads = heads
        self.projq = nn.Linear(dim, dim, bias=bias)
        self.projk = nn.Linear(dim, dim, bias=bias)
        self.projv = nn.Linear(dim, dim, bias=bias)
        self.proj = nn.Linear(dim, dim)

    def memory(self, y: Tensor) -> tuple[Tensor, Tensor]:
        """Normalised memory tokens [B,T,C] -> keys, values [B,H,T,d]."""
        return split_heads(self.projk(y), self.heads), split_heads(self.projv(y), self.heads)

    def forward(self, x: Tensor, k: Tensor, v: Tensor, fast: bool = True) -> Tensor:
        """x [B,Tq,C] attends to k/v [B,H,T,d] -> [B,Tq,C]."""
        return self.proj(merge_heads(attend(split_heads(self.projq(x), self.heads), k, v, fast)))


class DecoderBlock(nn.Module):
    """x += attn(norm1 x); x += cross(norm2 x, norm_y y); x += mlp(norm3 x). y passes unchanged."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c = cfg.dec_dim
        self.norm1 = layer_norm(c)
        self.attn = SelfAttention(c, cfg.dec_heads, bias=cfg.dec_qkv_bias)
        self.norm2 = layer_norm(c)
        self.norm_y = layer_norm(c)
        self.cross_attn = CrossAttention(c, cfg.dec_heads, bias=cfg.dec_qkv_bias)
        self.norm3 = layer_norm(c)
        self.mlp = Mlp(c, cfg.dec_mlp_hidden)

    def forward(self, x: Tensor, y: Tensor, fast: bool = True) -> Tensor:
        x = x + self.attn(self.norm1(x), fast)
        k, v = self.cross_attn.memory(self.norm_y(y))
        x = x + self.cross_attn(self.norm2(x), k, v, fast)
        return x + self.mlp(self.norm3(x))


def sincos_table(grid: int, dim: int) -> Tensor:
    """Fixed 2-D table [grid*grid, dim]: first half encodes the column, second half the row;
    each half is [sin(p*w_k)] + [cos(p*w_k)], w_k = 10000^(-k/(dim/4))."""
    quarter = dim // 4
    w = 10000.0 ** (-torch.arange(quarter, dtype=torch.float64) / quarter)
    rows, cols = torch.meshgrid(torch.arange(grid), torch.arange(grid), indexing="ij")

    def half(p: Tensor) -> Tensor:
        angle = p.reshape(-1, 1).double() * w
        return torch.cat([angle.sin(), angle.cos()], dim=1)

    return torch.cat([half(cols), half(rows)], dim=1).float()


class PairClassifier(nn.Module):
    """Decoder parameters and arithmetic; `PairVPR` adds the encoder and the global head."""

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        c = cfg.dec_dim
        self.decoder_embed = nn.Linear(cfg.embed_dim, c)
        self.decoder_clstoken = nn.Parameter(torch.zeros(1, 1, c))
        table = sincos_table(cfg.dec_pos_grid, c)
        self.register_buffer("dec_pos_embed", table)
        self.register_buffer("dec_pos_embed_cls", torch.cat([torch.zeros(1, c), table]))
        self.dec_blocks = nn.ModuleList(DecoderBlock(cfg) for _ in range(cfg.dec_depth))
        self.dec_norm = layer_norm(c)
        self.classvprmodule = nn.Sequential(
            nn.Linear(c, cfg.cls_hidden), nn.ReLU(), nn.Linear(cfg.cls_hidden, 1)
        )
        self._dec_pos_cache: dict[tuple, tuple[Tensor, Tensor]] = {}
        for module in (self.decoder_embed, self.dec_blocks, self.dec_norm, self.classvprmodule):
            module.apply(init_weights)
        nn.init.normal_(self.decoder_clstoken, std=1e-6)

    @property
    def decoder(self) -> PairClassifier:
        """The decoder view (`model.decoder.forward_tokens`); its parameters are top-level."""
        return self

    # ---- inputs ----------------------------------------------------------------------------
    def dec_positions(self, n: int) -> tuple[Tensor, Tensor]:
        """(table with a zero cls row [1+n, C], patch table [n, C]) for n tokens on a square grid,
        resized bicubically from the stored grid when it differs."""
        table = self.dec_pos_embed
        if table.shape[0] == n:
            return self.dec_pos_embed_cls, table
        key = (n, tensor_version(table), table.device, table.dtype)
        if key not in self._dec_pos_cache:
            side, new = math.isqrt(table.shape[0]), math.isqrt(n)
            if new * new != n:
                raise ValueError(f"{n} decoder tokens do not form a square grid")
            grid = table.float().reshape(1, side, side, -1).permute(0, 3, 1, 2)
            grid = F.interpolate(grid, size=(new, new), mode="bicubic", align_corners=False)
            resized = grid.permute(0, 2, 3, 1).reshape(n, -1).to(table.dtype)
            self._dec_pos_cache = {key: (torch.cat([resized[:1] * 0, resized]), resized)}
        return self._dec_pos_cache[key]

    def first_input(self, embedded: Tensor, use_cls: bool = True) -> Tensor:
        """Decoder-embedded tokens [B,N,C] -> the first image's stream [B,1+N,C] (or [B,N,C])."""
        pos_cls, pos = self.dec_positions(embedded.shape[1])
        if not use_cls:
            return embedded + pos
        cls = self.decoder_clstoken.expand(embedded.shape[0], -1, -1).to(embedded.dtype)
        return torch.cat([cls, embedded], dim=1) + pos_cls

    def second_input(self, embedded: Tensor) -> Tensor:
        return embedded + self.dec_positions(embedded.shape[1])[1]

    # ---- plain path ---------------------------------------------------------------------
    def forward_tokens(
        self, first: Tensor, second: Tensor, use_cls: bool = True, fast: bool = True
    ) -> Tensor:
        """Encoder tokens first/second [B,N,D] -> decoded first-image tokens after `dec_norm`,
        [B,1+N,C] with the class token first (use_cls) or [B,N,C] (stage-one training)."""
        x = self.first_input(self.decoder_embed(first), use_cls)
        y = self.second_input(self.decoder_embed(second))
        for block in self.dec_blocks:
            x = block(x, y, fast)
        return self.dec_norm(x)

    def pair_logits(self, first: Tensor, second: Tensor, fast: bool = True) -> Tensor:
        """One direction: first [B,N,D] with the class token, second [B,N,D] as memory -> [B]."""
        cls = self.forward_tokens(first, second, use_cls=True, fast=fast)[:, 0]
        return self.classvprmodule(cls).squeeze(-1)

    def pair_scores_reference(self, query: Tensor, cands: Tensor) -> Tensor:
        """Plain path: one pair and one direction at a time. query [N,D], cands [K,N,D] -> [K]."""
        q = query.unsqueeze(0)
        scores = [
            self.pair_logits(q, c[None], fast=False) + self.pair_logits(c[None], q, fast=False)
            for c in cands
        ]
        return torch.cat(scores) if scores else query.new_zeros(0)

    # ---- fast path -----------------------------------------------------------------------
    def pair_scores(self, query: Tensor, cands: Tensor, chunk: int | None = None) -> Tensor:
        """Bidirectional score logit(q,c) + logit(c,q): query [N,D], cands [K,N,D] -> [K].
        Candidates go through in chunks of `chunk` ([2*chunk, 1+N, 4C] activations at most).
        Default: 2 on a CPU, where larger chunks fall out of cache (ViT-B/322 measured 0.82x the
        reference per candidate at 2, 0.94x at 8, 1.0x at 16), and 32 on a GPU."""
        if cands.shape[0] == 0:
            return query.new_zeros(0)
        if chunk is None:
            chunk = 32 if query.is_cuda else 2
        eq = self.decoder_embed(query.unsqueeze(0))  # computed once for every candidate
        x_query = self.first_input(eq)
        x_query = x_query + self.dec_blocks[0].attn(self.dec_blocks[0].norm1(x_query))
        memory_query = self._query_memory(self.second_input(eq))
        out = [
            self._score_chunk(x_query, memory_query, cands[i : i + chunk])
            for i in range(0, cands.shape[0], chunk)
        ]
        return torch.cat(out)

    def _query_memory(self, y: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Keys/values of the query as cross-attention memory, once per block ([1,H,N,d] each)."""
        return [blk.cross_attn.memory(blk.norm_y(y)) for blk in self.dec_blocks]

    def _score_chunk(
        self, x_query: Tensor, memory_query: list[tuple[Tensor, Tensor]], cands: Tensor
    ) -> Tensor:
        k = cands.shape[0]
        ec = self.decoder_embed(cands)
        y_cands = self.second_input(ec)  # memory of direction 1 (query first)
        x_cands = self.first_input(ec)  # stream of direction 2 (candidate first)
        blk0 = self.dec_blocks[0]
        x_cands = x_cands + blk0.attn(blk0.norm1(x_cands))
        x = torch.cat([x_query.expand(k, -1, -1), x_cands])  # [2K, 1+N, C]
        last = len(self.dec_blocks) - 1
        for i, blk in enumerate(self.dec_blocks):
            if i > 0:  # block 0's self-attention ran above
                delta = blk.attn(blk.norm1(x), first_row_only=i == last)
                x = (x[:, :1] if i == last else x) + delta
            elif i == last:
                x = x[:, :1]
            heads = blk.cross_attn.heads
            q = split_heads(blk.cross_attn.projq(blk.norm2(x)), heads)
            k1, v1 = blk.cross_attn.memory(blk.norm_y(y_cands))
            k2, v2 = memory_query[i]
            attended = torch.cat(
                [
                    attend(q[:k], k1, v1),
                    attend(q[k:], k2.expand(k, -1, -1, -1), v2.expand(k, -1, -1, -1)),
                ]
            )
            x = x + blk.cross_attn.proj(merge_heads(attended))
            x = x + blk.mlp(blk.norm3(x))
        logits = self.classvprmodule(self.dec_norm(x[:, 0])).squeeze(-1)
        return logits[:k] + logits[k:]
