"""Camera image -> network input: RGB, resized to size x size (aspect not kept), bilinear with
antialiasing (as PIL/torchvision resize), scaled to [0,1], ImageNet mean/std."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from pair_vpr_ros.errors import ImageConversionError

MEAN = (0.485, 0.456, 0.406)
STD = (0.229, 0.224, 0.225)


def as_rgb(image: np.ndarray) -> np.ndarray:
    """Accept [H,W,3] RGB, [H,W] or [H,W,1] grey (replicated) and [H,W,4] RGBA (alpha dropped);
    uint8 only. Anything else raises ImageConversionError."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        kind = image.dtype if isinstance(image, np.ndarray) else type(image).__name__
        raise ImageConversionError(f"preprocess expects a uint8 numpy image, got {kind}")
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[2] not in (1, 3, 4) or min(image.shape[:2]) < 1:
        raise ImageConversionError(
            f"preprocess expects an image of shape [H,W,3] (or grey [H,W] / RGBA [H,W,4]), "
            f"got {image.shape}"
        )
    if image.shape[2] == 1:
        return np.repeat(image, 3, axis=2)
    return image[:, :, :3]


def preprocess(rgb: np.ndarray, size: int = 322) -> Tensor:
    """RGB uint8 [H,W,3] (grey/RGBA converted, see `as_rgb`) -> float32 [3,size,size]."""
    return preprocess_batch([rgb], size)[0]


def preprocess_batch(images: Sequence[np.ndarray], size: int = 322) -> Tensor:
    """A list of RGB uint8 images of any sizes -> float32 [B,3,size,size]."""
    mean = torch.tensor(MEAN).view(3, 1, 1)
    std = torch.tensor(STD).view(3, 1, 1)
    out = torch.empty(len(images), 3, size, size)
    for i, image in enumerate(images):
        x = torch.from_numpy(np.ascontiguousarray(as_rgb(image))).permute(2, 0, 1).float()
        if x.shape[1:] != (size, size):
            x = F.interpolate(
                x[None], size=(size, size), mode="bilinear", align_corners=False, antialias=True
            )[0]
        out[i] = (x / 255.0 - mean) / std
    return out
