"""Synthetic calibration images for static int8 quantization.

Static int8 fixes each activation's range from a few sample inputs. Random noise gives ranges
unlike a camera's (perf-facts: descriptor cosine ~0.998), so these images have what street and
indoor frames have: smooth shading, large flat regions, straight edges, repeated windows, a
horizon. They are made here (the core may not use the demo world) and are the same on every
run (fixed seeds). Images of the robot's own camera can replace them:
`offline/bags/calibration.py` (parameter `openvino_calibration`).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from pair_vpr_ros.model.preprocess import preprocess_batch

CALIBRATION_IMAGES = 16  # encoder samples; the re-rank graph gets half as many pairs


def synthetic_scene(seed: int, height: int = 240, width: int = 320) -> np.ndarray:
    """One made-up scene, RGB uint8 [height, width, 3]: sky and ground gradients, a few
    box-shaped buildings with window grids, blurred to camera-like sharpness, plus sensor
    noise."""
    rng = np.random.default_rng(seed)
    horizon = int(height * rng.uniform(0.3, 0.6))
    img = np.zeros((height, width, 3), np.float32)
    ramp = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None, None]
    sky, ground = rng.uniform(40, 230, (2, 3)).astype(np.float32)
    img[:] = sky * (1 - 0.5 * ramp) + ground * 0.5 * ramp
    img[horizon:] = ground * (0.6 + 0.4 * ramp[horizon:])
    for _ in range(int(rng.integers(2, 7))):
        x0, x1 = sorted(rng.integers(0, width, 2))
        top = int(rng.integers(0, horizon))
        bottom = int(min(height, horizon + rng.integers(0, height // 4)))
        colour = rng.uniform(20, 240, 3)
        cv2.rectangle(img, (int(x0), top), (int(x1), bottom), colour.tolist(), -1)
        step = int(rng.integers(8, 24))
        window = (colour * rng.uniform(0.2, 0.6)).tolist()
        for y in range(top + 4, bottom - step, step):
            for x in range(int(x0) + 4, int(x1) - step, step):
                cv2.rectangle(img, (x, y), (x + step // 2, y + step // 2), window, -1)
    img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 1.5))
    img += rng.normal(0.0, 3.0, img.shape).astype(np.float32)
    return np.clip(img, 0, 255).astype(np.uint8)


def synthetic_calibration(count: int, size: int, seed: int = 0) -> torch.Tensor:
    """`count` synthetic scenes preprocessed for the network -> float32 [count,3,size,size]."""
    return preprocess_batch([synthetic_scene(seed + i) for i in range(count)], size)
