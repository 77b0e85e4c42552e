"""Torch device names given by users (node parameter, CLI flags), checked before any work."""

from __future__ import annotations

import torch

from .errors import ConfigError


def check_device(device: str) -> torch.device:
    """`device` as a torch.device; ConfigError for unknown names, and for CUDA where none is."""
    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError) as err:
        raise ConfigError(f"device {device!r} is not a torch device (cpu, cuda, cuda:1)") from err
    if parsed.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {device!r}: CUDA is not available here; use cpu")
    if parsed.type not in ("cpu", "cuda"):
        raise ConfigError(f"device {device!r}: only cpu and cuda devices are supported")
    return parsed
