"""How a model's two stages rank places on a held-out place dataset (ROOT/<place>/<k>.png).

A third of the views (two of each place's six, in varying lightings) are queries against all
other views (cost: the pair classifier runs on queries x K pairs). For each query the global
descriptor gives the top-K candidates; "global" keeps the most similar, "re-ranked" the one
with the highest pair score. Each query's kept match, with its score, is one detection, as a
loop closure is: average precision (AP) and recall at precision 0.9 are computed over all
queries ranked by that score.

Two probes of the pair score (issue 24):
- lighting AUC: on the candidates of *other* places, how well the pair score tells a candidate
  in the query's lighting from one in another lighting (0.5 = not at all: no lighting
  shortcut). View ``k.png`` of the demo place datasets is lit by lighting ``k mod 3``;
- identical: the score of a view against itself, and the share of queries for which it is at
  least the best true revisit's score among the candidates.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from pair_vpr_ros.errors import DatasetError
from pair_vpr_ros.learn.image_files import read_rgb
from pair_vpr_ros.learn.places import load_place_folders
from pair_vpr_ros.learn.train.data import view_condition
from pair_vpr_ros.model import PairVPR, preprocess_batch


@dataclass(frozen=True)
class HeldoutViews:
    """Flat views of a place dataset: paths, place labels [M], lighting conditions [M] and the
    query views [Q] (the k-th view of place p where (k + p) mod 3 = 0)."""

    paths: list[Path]
    labels: np.ndarray
    conds: np.ndarray
    queries: np.ndarray

    @classmethod
    def load(cls, root: str | Path, conditions: int = 3) -> HeldoutViews:
        places = load_place_folders(root).places
        paths = [v for p in places for v in p]
        if len(places) < 2:
            raise DatasetError(f"{root}: a held-out set needs >= 2 places, found {len(places)}")
        labels = np.array([i for i, p in enumerate(places) for _ in p])
        conds = np.array([view_condition(v, conditions) for v in paths])
        queries, start = [], 0
        for p, views in enumerate(places):
            queries += [start + k for k in range(len(views)) if (k + p) % 3 == 0]
            start += len(views)
        return cls(paths, labels, conds, np.array(queries))


def average_precision(
    scores: np.ndarray, correct: np.ndarray, positives: int | None = None
) -> tuple[float, float]:
    """Detections (score [Q], correct [Q] bool) -> (AP, recall at precision >= 0.9) over
    ``positives`` queries with a true match (None: every query has one; 0: (0, 0))."""
    positives = len(scores) if positives is None else positives
    if positives == 0:
        return 0.0, 0.0
    order = np.argsort(-scores, kind="stable")
    hits = correct[order].astype(float)
    precision = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    recall = np.cumsum(hits) / positives
    ap = float((precision * hits).sum() / positives)
    ok = precision >= 0.9
    return ap, float(recall[ok].max()) if ok.any() else 0.0


def auc(scores: np.ndarray, positive: np.ndarray) -> float:
    """Probability that a positive outscores a negative (ties count half); nan if one is empty."""
    pos, neg = scores[positive], scores[~positive]
    if not len(pos) or not len(neg):
        return float("nan")
    # Mann-Whitney U with average ranks, so that equal scores count half
    _, inverse, counts = np.unique(
        np.concatenate([pos, neg]), return_inverse=True, return_counts=True
    )
    avg = (np.cumsum(counts) - counts + (counts - 1) / 2.0)[inverse]
    return float((avg[: len(pos)].sum() - len(pos) * (len(pos) - 1) / 2) / (len(pos) * len(neg)))


@torch.inference_mode()
def encode_views(
    model: PairVPR, paths: list[Path], batch: int = 64, grey: bool = False
) -> tuple[torch.Tensor, ...]:
    """Paths -> (dense [M,N,D], descriptors [M,C]) on the CPU, encoded at the model's image size
    on its device; ``grey``: of their grey versions, as the demo's mono8 bags and `images.convert`
    make them."""
    dense, desc = [], []
    for i in range(0, len(paths), batch):
        rgb = [read_rgb(p) for p in paths[i : i + batch]]
        if grey:
            rgb = [
                cv2.cvtColor(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB) for x in rgb
            ]
        images = preprocess_batch(rgb, model.config.image_size).to(model.device)
        d, g = model.encode(images)
        dense.append(d.float().cpu())
        desc.append(g.float().cpu())
    return torch.cat(dense), torch.cat(desc)


@torch.inference_mode()
def pair_scores(
    model: PairVPR,
    dense: torch.Tensor,
    first: torch.Tensor,
    second: torch.Tensor,
    chunk: int = 256,
) -> torch.Tensor:
    """Bidirectional pair scores logit(a,b) + logit(b,a) of the views first [P] and second [P]
    (indices into dense [M,N,D], on any device) -> [P] on the CPU, in chunks of ``chunk`` pairs
    run on the model's device."""
    out = []
    for i in range(0, len(first), chunk):
        a = dense[first[i : i + chunk]].to(model.device)
        b = dense[second[i : i + chunk]].to(model.device)
        out.append((model.pair_logits(a, b).float() + model.pair_logits(b, a).float()).cpu())
    return torch.cat(out)


@torch.inference_mode()
def measure(
    model: PairVPR, views: HeldoutViews, k: int = 10, grey: bool = False
) -> dict[str, float]:
    """Global vs re-ranked AP / R@1 and both probes on ``views`` (see the module docstring);
    ``grey``: every view in grey, queries and candidates alike (a mono8 camera)."""
    was_training = model.training
    model.eval()
    dense, desc = encode_views(model, views.paths, grey=grey)
    queries = torch.from_numpy(views.queries)
    sim = desc[queries] @ desc.T
    sim[torch.arange(len(queries)), queries] = -float("inf")
    k = min(k, len(views.paths) - 1)
    top_sim, cands = sim.topk(k, dim=1)
    pair = pair_scores(model, dense, queries.repeat_interleave(k), cands.flatten()).view(-1, k)
    same_view = pair_scores(model, dense, queries, queries)
    model.train(was_training)
    cands, pair, top_sim = cands.numpy(), pair.float().numpy(), top_sim.numpy()
    same_view = same_view.numpy()
    q_labels, q_conds = views.labels[views.queries], views.conds[views.queries]
    true = views.labels[cands] == q_labels[:, None]  # [Q,K]
    best = pair.argmax(axis=1)
    rows = np.arange(len(cands))
    g_ap, g_r90 = average_precision(top_sim[:, 0], true[:, 0])
    r_ap, r_r90 = average_precision(pair[rows, best], true[rows, best])
    negatives = ~true
    same_light = views.conds[cands] == q_conds[:, None]
    revisit = np.where(true, pair, -np.inf).max(axis=1)
    has_revisit = true.any(axis=1)
    return {
        "global_ap": g_ap,
        "rerank_ap": r_ap,
        "global_r@p90": g_r90,
        "rerank_r@p90": r_r90,
        "global_r@1": float(true[:, 0].mean()),
        "rerank_r@1": float(true[rows, best].mean()),
        "lighting_auc": auc(pair[negatives], same_light[negatives]),
        "lighting_auc_global": auc(top_sim[negatives], same_light[negatives]),
        "identical_score": float(same_view.mean()),
        "revisit_score": float(revisit[has_revisit].mean()) if has_revisit.any() else 0.0,
        "identical_ge_revisit": float((same_view >= revisit)[has_revisit].mean()),
    }
