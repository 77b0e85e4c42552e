"""`PairVPRModel`: the network as the rest of the package sees it.

The pipeline, the map builder, the replay and evaluation use only these members, so a back end
other than PyTorch's `PairVPR` (an OpenVINO or ONNX runtime, a remote model) plugs in by
implementing them. Training and the checkpoint code use `PairVPR` itself.

Optional members: `chunk_size` (int), for a back end compiled for a fixed number of candidates
per `pair_scores` call that pads shorter calls (`OpenVINOModel`); the re-rank budget then scores
whole chunks. `query_scorer(query [N,D])`, for the re-rank cascade (`rerank_cascade`): an
object with `scores(cands [K,N,D]) -> [K]` (both directions, as `pair_scores`) and
`logits(cands, first) -> [K]` (one direction: `first` "query" gives logit(q,c), "candidate"
logit(c,q)), the query's side computed once; without it the cascade scores in full.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import torch
from torch import Tensor

from pair_vpr_ros.model.config import ModelConfig


@runtime_checkable
class PairVPRModel(Protocol):
    """Encoder + global head + pair classifier behind two calls. Callers wrap the calls in
    `torch.inference_mode()` and keep the model on one thread at a time."""

    @property
    def config(self) -> ModelConfig:
        """Input size (`image_size`), descriptor size (`desc_dim`), dense width (`embed_dim`)."""
        ...

    @property
    def fingerprint(self) -> str:
        """Which descriptors this model makes (weights, input size, sizes); maps record it."""
        ...

    @property
    def num_patches(self) -> int:
        """N, dense tokens per image at `config.image_size`."""
        ...

    @property
    def device(self) -> torch.device:
        """Where `encode` wants its images and `pair_scores` its tokens."""
        ...

    @property
    def dense_dtype(self) -> torch.dtype:
        """The dtype `pair_scores` takes its dense tokens in."""
        ...

    def encode(self, images: Tensor) -> tuple[Tensor, Tensor]:
        """Normalised images [B,3,S,S] -> (dense tokens [B,N,D], L2-normalised global
        descriptors [B,desc_dim])."""
        ...

    def pair_scores(self, query: Tensor, cands: Tensor, chunk: int | None = None) -> Tensor:
        """Query dense [N,D] against candidates [K,N,D] -> logit(q,c) + logit(c,q), [K]."""
        ...
