"""Losses of both stages: masked patch reconstruction (stage one), multi-similarity on global
descriptors and batch-hard pair classification (stage two)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.model.config import PATCH


def patchify(images: Tensor, patch: int = PATCH) -> Tensor:
    """[B,3,H,W] -> [B,N,patch*patch*3]; patches row-major, inside a patch (row, col, channel)."""
    b, c, h, w = images.shape
    gh, gw = h // patch, w // patch
    x = images.reshape(b, c, gh, patch, gw, patch)
    return x.permute(0, 2, 4, 3, 5, 1).reshape(b, gh * gw, patch * patch * c)


def random_patch_mask(
    batch: int,
    num_patches: int,
    ratio: float,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> Tensor:
    """[B,N] bool, exactly round(ratio*N) (at least 1) True per row, chosen independently."""
    if not 0.0 < ratio < 1.0:
        raise ConfigError(f"mask ratio {ratio} must be in (0, 1)")
    count = max(1, round(ratio * num_patches))
    noise = torch.rand(batch, num_patches, generator=generator)
    ranks = noise.argsort(dim=1).argsort(dim=1)
    return (ranks < count).to(device)


def masked_patch_mse(pred: Tensor, images: Tensor, mask: Tensor, eps: float = 1e-6) -> Tensor:
    """Mean squared error over masked patches only.

    pred [B,N,P*P*3], images [B,3,H,W] (the unmasked first images), mask [B,N] bool. Targets are
    normalised per patch: (x - mean) / sqrt(var + eps) over the patch's P*P*3 values."""
    target = patchify(images.float(), int(round((pred.shape[-1] // 3) ** 0.5)))
    mean = target.mean(dim=-1, keepdim=True)
    var = target.var(dim=-1, keepdim=True)
    target = (target - mean) / (var + eps).sqrt()
    per_patch = ((pred.float() - target) ** 2).mean(dim=-1)  # [B,N]
    weight = mask.to(per_patch.dtype)
    return (per_patch * weight).sum() / weight.sum().clamp_min(1.0)


def _metric_learning():
    try:
        from pytorch_metric_learning import distances, losses, miners
    except ImportError as err:
        raise ConfigError(
            "stage-two training needs pytorch-metric-learning: pip install 'pair_vpr_ros[train]'"
        ) from err
    return distances, losses, miners


class MultiSimilarityObjective:
    """Multi-similarity loss on pairs chosen by the multi-similarity miner, dot-product similarity
    (descriptors are L2-normalised). Call: (desc [M,C], labels [M]) -> (loss, mined pair count)."""

    def __init__(
        self, alpha: float = 1.0, beta: float = 50.0, base: float = 0.0, epsilon: float = 0.1
    ) -> None:
        distances, losses, miners = _metric_learning()
        self.miner = miners.MultiSimilarityMiner(
            epsilon=epsilon, distance=distances.DotProductSimilarity()
        )
        self.loss = losses.MultiSimilarityLoss(
            alpha=alpha, beta=beta, base=base, distance=distances.DotProductSimilarity()
        )

    def __call__(self, desc: Tensor, labels: Tensor) -> tuple[Tensor, int]:
        mined = self.miner(desc, labels)
        pairs = int(mined[0].numel() + mined[2].numel())  # (anchor, pos) + (anchor, neg)
        return self.loss(desc, labels, mined), pairs


def batch_hard_indices(
    sim: Tensor, anchor_labels: Tensor, labels: Tensor, anchor_index: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """For each anchor the hardest positive (least similar same-place) and hardest negative (most
    similar other-place) item.

    sim [A,M] anchor-to-all similarity, anchor_labels [A], labels [M], anchor_index [A] (each
    anchor's own column) -> (positive [A], negative [A], valid [A] bool: both exist)."""
    rows = torch.arange(sim.shape[0], device=sim.device)
    same = anchor_labels[:, None] == labels[None, :]
    same[rows, anchor_index] = False
    other = anchor_labels[:, None] != labels[None, :]
    inf = torch.finfo(sim.dtype).max
    positive = sim.masked_fill(~same, inf).argmin(dim=1)
    negative = sim.masked_fill(~other, -inf).argmax(dim=1)
    return positive, negative, same.any(dim=1) & other.any(dim=1)


def relation_hard_indices(
    sim: Tensor,
    anchor_labels: Tensor,
    labels: Tensor,
    anchor_index: Tensor,
    anchor_conds: Tensor,
    conds: Tensor,
    random_negatives: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Batch-hard mining without the condition shortcut: every anchor's positive and negative
    have the same condition relation to it, both in its condition (even anchors) or both in
    another one (odd anchors), so "other lighting" cannot tell them apart. An anchor that lacks
    one of the two under its relation takes the other relation; unknown conditions (-1) count as
    the same condition as any other unknown. ``random_negatives``: a random other-place item
    of that relation instead of the hardest (an easier task for a classifier that starts from
    nothing).

    sim [A,M], anchor_labels [A], labels [M], anchor_index [A], anchor_conds [A], conds [M]
    -> (positive [A], negative [A], valid [A] bool), as `batch_hard_indices`."""
    rows = torch.arange(sim.shape[0], device=sim.device)
    same_place = anchor_labels[:, None] == labels[None, :]
    same_place[rows, anchor_index] = False
    other_place = anchor_labels[:, None] != labels[None, :]
    same_cond = anchor_conds[:, None] == conds[None, :]
    want_same = (rows % 2 == 0)[:, None]
    inf = torch.finfo(sim.dtype).max
    out = []
    for relation in (same_cond == want_same, same_cond != want_same):
        pos_ok, neg_ok = same_place & relation, other_place & relation
        pos = sim.masked_fill(~pos_ok, inf).argmin(dim=1)
        neg_score = torch.rand_like(sim) if random_negatives else sim
        neg = neg_score.masked_fill(~neg_ok, -inf).argmax(dim=1)
        out.append((pos, neg, pos_ok.any(dim=1) & neg_ok.any(dim=1)))
    (pos, neg, ok), (pos2, neg2, ok2) = out
    pos, neg = torch.where(ok, pos, pos2), torch.where(ok, neg, neg2)
    return pos, neg, ok | ok2


def same_condition_negatives(
    anchor_labels: Tensor, labels: Tensor, anchor_conds: Tensor | None, conds: Tensor | None
) -> Tensor:
    """For each anchor a random item of another place in the anchor's condition (any other
    place when conditions are unknown or none is left): the negatives that balance identical
    pairs, which are all in one lighting, so that "same lighting" does not predict "same
    place". anchor_labels [A], labels [M], conditions [A] / [M] -> indices [A]."""
    other = anchor_labels[:, None] != labels[None, :]
    ok = other
    if anchor_conds is not None and conds is not None:
        same = other & (anchor_conds[:, None] == conds[None, :])
        ok = torch.where(same.any(dim=1, keepdim=True), same, other)
    return torch.rand(ok.shape, device=labels.device).masked_fill(~ok, -1.0).argmax(dim=1)


def random_positive_indices(
    anchor_labels: Tensor,
    labels: Tensor,
    anchor_index: Tensor,
    generator: torch.Generator | None = None,
) -> Tensor:
    """For each anchor a uniformly random other item of its place: anchor_labels [A], labels [M],
    anchor_index [A] -> [A] (an anchor without one gets an arbitrary index; `batch_hard_indices`
    says which are valid)."""
    rows = torch.arange(anchor_labels.shape[0], device=labels.device)
    same = anchor_labels[:, None] == labels[None, :]
    same[rows, anchor_index] = False
    noise = torch.rand(same.shape, generator=generator).to(labels.device)
    return noise.masked_fill(~same, -1.0).argmax(dim=1)


def pair_bce(positive_logits: Tensor, negative_logits: Tensor) -> Tensor:
    """Binary cross-entropy: same-place logits -> 1, other-place logits -> 0 (mean over all)."""
    logits = torch.cat([positive_logits, negative_logits]).float()
    targets = torch.cat([torch.ones_like(positive_logits), torch.zeros_like(negative_logits)])
    return F.binary_cross_entropy_with_logits(logits, targets.float())
