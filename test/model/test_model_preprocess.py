"""Camera image -> normalised network input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pair_vpr_ros.errors import ImageConversionError
from pair_vpr_ros.model import preprocess, preprocess_batch
from pair_vpr_ros.model.preprocess import MEAN, STD


def test_odd_sizes_resize_to_square():
    rgb = np.random.default_rng(0).integers(0, 256, (37, 53, 3), dtype=np.uint8)
    assert preprocess(rgb).shape == (3, 322, 322)
    assert preprocess(rgb, size=56).shape == (3, 56, 56)


def test_normalisation_values():
    out = preprocess(np.full((20, 30, 3), 255, np.uint8), size=28)
    expected = [(1 - m) / s for m, s in zip(MEAN, STD, strict=True)]
    assert torch.allclose(out[:, 5, 5], torch.tensor(expected))
    same = preprocess(np.zeros((28, 28, 3), np.uint8), size=28)  # no resize at the target size
    assert torch.allclose(
        same[:, 0, 0], torch.tensor([-m / s for m, s in zip(MEAN, STD, strict=True)])
    )


def test_grey_and_rgba_are_converted():
    grey = np.random.default_rng(1).integers(0, 256, (30, 40), dtype=np.uint8)
    rgb = np.repeat(grey[:, :, None], 3, axis=2)
    rgba = np.concatenate([rgb, np.zeros((30, 40, 1), np.uint8)], axis=2)
    assert torch.equal(preprocess(grey, 28), preprocess(rgb, 28))
    assert torch.equal(preprocess(grey[:, :, None], 28), preprocess(rgb, 28))
    assert torch.equal(preprocess(rgba, 28), preprocess(rgb, 28))
    assert preprocess_batch([grey, rgba], 28).shape == (2, 3, 28, 28)


@pytest.mark.parametrize(
    "image,message",
    [
        (np.zeros((4, 4, 3), np.float32), "expects a uint8 numpy image, got float32"),
        ([[0]], "expects a uint8 numpy image, got list"),
        (np.zeros((4, 4, 2), np.uint8), r"got \(4, 4, 2\)"),
        (np.zeros((0, 4, 3), np.uint8), r"got \(0, 4, 3\)"),
    ],
)
def test_bad_images_are_rejected(image, message):
    with pytest.raises(ImageConversionError, match=message):
        preprocess(image)
