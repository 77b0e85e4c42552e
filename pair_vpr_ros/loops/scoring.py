"""Encoding frames for the map and pair-scoring a query against stored dense tokens.

The node, the replay, the map builder and `pairvpr-eval` all score through these functions, so a
query scores exactly like the same image stored in the map.
"""

from __future__ import annotations

import numpy as np
import torch

from pair_vpr_ros.model import PairVPRModel
from pair_vpr_ros.place_map import PlaceMap


def encode_for_map(model: PairVPRModel, images: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Preprocessed images [B,3,S,S] -> what the map stores: dense tokens float16 [B,N,D] and
    descriptors float32 [B,desc_dim]. Queries are rounded to float16 too, so a query scores
    exactly like the same image stored in the map."""
    with torch.inference_mode():
        dense, desc = model.encode(images.to(model.device, non_blocking=True))
    return dense.to(torch.float16).cpu().numpy(), desc.float().cpu().numpy()


def map_pair_scores(
    model: PairVPRModel,
    place_map: PlaceMap,
    dense: np.ndarray,
    ids: list[int],
    chunk: int | None = None,
) -> np.ndarray:
    """Query dense [N,D] against the dense tokens of map keyframes ``ids`` -> bidirectional
    pair scores float32 [K] (the node's re-ranking, and ``pairvpr-eval``'s)."""
    return dense_pair_scores(model, dense, place_map.get_dense(ids), chunk)


def dense_pair_scores(
    model: PairVPRModel, dense: np.ndarray, candidates: np.ndarray, chunk: int | None = None
) -> np.ndarray:
    """Query dense [N,D] against candidate dense tokens [K,N,D] -> pair scores float32 [K]."""
    device, dtype = model.device, model.dense_dtype
    q = torch.from_numpy(np.asarray(dense)).to(device=device, dtype=dtype)
    c = torch.from_numpy(np.asarray(candidates)).to(device=device, dtype=dtype)
    with torch.inference_mode():
        return model.pair_scores(q, c, chunk=chunk).float().cpu().numpy()


class QueryDirections:
    """One query's pair decoder, one direction at a time (the re-rank cascade): the query's
    side is computed at the first call and kept for the next ones. Needs a model with
    `query_scorer` (`supported`)."""

    def __init__(self, model: PairVPRModel, dense: np.ndarray) -> None:
        self.model, self.dense, self._scorer = model, dense, None

    @staticmethod
    def supported(model: PairVPRModel) -> bool:
        return callable(getattr(model, "query_scorer", None))

    def logits(self, candidates: np.ndarray, first: str) -> np.ndarray:
        """Candidate dense tokens [K,N,D] -> logits float32 [K] of the direction whose first
        image is `first` ("query": logit(q,c); "candidate": logit(c,q))."""
        device, dtype = self.model.device, self.model.dense_dtype
        c = torch.from_numpy(np.asarray(candidates)).to(device=device, dtype=dtype)
        with torch.inference_mode():
            if self._scorer is None:
                q = torch.from_numpy(np.asarray(self.dense)).to(device=device, dtype=dtype)
                self._scorer = self.model.query_scorer(q)
            return self._scorer.logits(c, first).float().cpu().numpy()
