"""Torch device names given by users (node parameter, CLI flags), checked before any work.

The one parser for the node, the replay, the evaluation and training: ``auto``, ``cpu``, ``cuda``,
``cuda:N``.
"""

from __future__ import annotations

import torch

from pair_vpr_ros.errors import ConfigError


def check_device(device: str | torch.device, local_rank: int = 0) -> torch.device:
    """``device`` as a torch.device. ``auto``: CUDA when available, else the CPU; ``auto`` and a
    bare ``cuda`` mean ``cuda:<local_rank>`` (this process's GPU under torchrun). ConfigError for
    unknown names, other device types, and CUDA where there is none."""
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError, TypeError) as err:
        raise ConfigError(
            f"device {device!r} is not a torch device (auto, cpu, cuda, cuda:1)"
        ) from err
    if parsed.type not in ("cpu", "cuda"):
        raise ConfigError(f"device {device!r}: only cpu and cuda devices are supported")
    if parsed.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {device!r}: CUDA is not available here; use cpu")
    if parsed.type == "cuda" and parsed.index is None:
        parsed = torch.device("cuda", local_rank)
    if parsed.type == "cuda" and parsed.index >= torch.cuda.device_count():
        raise ConfigError(
            f"device {device!r}: there is no {parsed} here ({torch.cuda.device_count()} CUDA "
            "devices, numbered from cuda:0)"
        )
    return parsed
