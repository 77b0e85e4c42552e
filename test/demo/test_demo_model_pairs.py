"""Issue 24, point 3: with the shipped demo model and `config/demo.yaml` a frame scores at least as
high against itself and against a near-identical copy as against its true revisit, so that an
exact repeat of a keyframe is a loop. The detector's re-rank score (pair + global_weight x
similarity) does so for every frame. The pair score alone does for 12 of these 16 (measured
2026-11-26; the test allows 12): the drive stage's longer training lifts revisits' scores as far
as identical pairs', which binary cross-entropy does not order (two models before it: 16 and
15; docs/training.md). On the tests' world (seed 11: never trained on, not the demo's 7 or 8).

Skipped only while the shipped model predates the recipe that trains identical pairs (its
summary has no ``twin_share``): that model scores a frame against itself at about -1.9 and a
revisit at about 0.6 (docs/training.md)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import pair_vpr_ros
from pair_vpr_ros.demo import generate_world, render_frame
from pair_vpr_ros.model import load_pairvpr, preprocess_batch
from pair_vpr_ros.params.configs import detector_config
from pair_vpr_ros.params.file import read_params_file

ASSET = Path(pair_vpr_ros.__file__).resolve().parent / "demo" / "assets" / "demo-small.pth"


def _trained_on_identical_pairs() -> bool:
    summary = json.loads(ASSET.with_suffix(".json").read_text())
    return summary.get("stage2_config", {}).get("twin_share", 0.0) > 0


@pytest.mark.slow
@pytest.mark.skipif(
    not _trained_on_identical_pairs(), reason="shipped model predates identical-pair training"
)
def test_a_repeat_scores_at_least_as_high_as_a_revisit() -> None:
    model = load_pairvpr(ASSET)
    config = detector_config(read_params_file(ASSET.parents[3] / "config" / "demo.yaml"))
    world = generate_world(11)
    later = np.flatnonzero(world.revisit_of >= 0)[::15][:16]
    rng = np.random.default_rng(0)
    pair, sims = [], []
    for i in later:
        rgb = render_frame(world, int(i))
        noisy = np.clip(rgb.astype(int) + rng.integers(-2, 3, rgb.shape), 0, 255).astype(np.uint8)
        images = [rgb, noisy, render_frame(world, int(world.revisit_of[i]))]
        with torch.inference_mode():
            dense, desc = model.encode(preprocess_batch(images, model.config.image_size))
            pair.append(model.pair_scores(dense[0].float(), dense.float()).tolist())
            sims.append((desc.float() @ desc[0].float()).tolist())
    pair = np.array(pair)  # [frames, (identical, near-identical, revisit)]
    score = pair + config.global_weight * np.array(sims)  # what the detector ranks and accepts
    assert len(pair) == 16
    assert (score[:, 0] >= score[:, 2]).all() and (score[:, 1] >= score[:, 2]).all(), score
    assert (score[:, :2] >= config.score_threshold).all(), score  # a repeat is accepted
    assert (pair[:, 0] >= pair[:, 2]).sum() >= 12, pair
    assert (pair[:, 1] >= pair[:, 2]).sum() >= 12, pair
