"""Stage-two sanity check: on a tiny set where the answer is known, the pair classifier learns.

Eight synthetic places (a coarse colour layout each, shifted and noised per view,
`synthetic_data.place_image`); the tiny network trains on four views of each with the stage-two
objective, then scores unseen views: same place -> logit > 0, other place -> logit < 0. A pair
classifier that cannot learn (frozen decoder, detached pair loss, an init whose attention never
leaves uniform) stays at chance, 0.5.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from synthetic_data import place_image

from pair_vpr_ros.learn.train.common import DistContext, set_trainable
from pair_vpr_ros.learn.train.stage2 import Stage2Config, Stage2Objective
from pair_vpr_ros.model import ModelConfig, PairVPR, build_pairvpr, preprocess

PLACES = 8


def _views(views: range) -> torch.Tensor:
    """[PLACES, len(views), 3, 56, 56] normalised images."""
    return torch.stack(
        [
            torch.stack([preprocess(place_image(p, v), size=56) for v in views])
            for p in range(PLACES)
        ]
    )


def pair_accuracy(model: PairVPR, views: torch.Tensor) -> float:
    """Balanced accuracy at logit 0 over every (view 0 of place a, view 1 of place b) pair."""
    model.eval()
    with torch.no_grad():
        dense, _ = model.encode(views.flatten(0, 1))
        dense = dense.view(*views.shape[:2], *dense.shape[1:])
        first = dense[:, 0].repeat_interleave(PLACES, dim=0)  # a = row // PLACES
        second = dense[:, 1].repeat(PLACES, 1, 1)  # b = row % PLACES
        logits = model.pair_logits(first, second).view(PLACES, PLACES)
    model.train()
    same = torch.eye(PLACES, dtype=torch.bool)
    return 0.5 * float((logits[same] > 0).float().mean() + (logits[~same] < 0).float().mean())


@pytest.fixture
def one_thread() -> Iterator[None]:
    """Tiny matrices: a second thread only adds waiting on a busy machine (10x slower here)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.usefixtures("one_thread")
def test_pair_classifier_learns_a_known_answer(tmp_path: Path) -> None:
    torch.manual_seed(0)
    train, held_out = _views(range(4)), _views(range(4, 6))
    labels = torch.arange(PLACES)[:, None].expand(PLACES, 4).flatten()
    model = build_pairvpr(ModelConfig.tiny(), seed=0).train()
    set_trainable(model, 2, train_blocks=2)
    objective = Stage2Objective(model, Stage2Config(data=[], out_dir=tmp_path), DistContext())
    opt = torch.optim.AdamW([p for p in objective.parameters() if p.requires_grad], lr=1e-3)
    before = pair_accuracy(model, held_out)
    losses = []
    for _ in range(40):
        loss = objective(train.flatten(0, 1), labels)
        opt.zero_grad()
        loss["loss"].backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)  # as the trainer does
        opt.step()
        losses.append(float(loss["pair"]))
    after = pair_accuracy(model, held_out)
    assert before < 0.65, f"untrained classifier already at {before:.2f}"
    assert after >= 0.75, f"pair accuracy {before:.2f} -> {after:.2f} in 40 steps"
    assert sum(losses[-5:]) / 5 < 0.5 * sum(losses[:5]) / 5  # BCE at chance is 0.693
