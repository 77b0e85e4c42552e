"""The network every entry point runs: one way to find the weights, one loader.

Used by the node (parameter ``weights``), ``pairvpr-bag-replay`` and ``pairvpr-eval``
(``--weights``); the node's map build runs the node's model. Where the weights come from, first
match wins (a robot has one model: set it once, not in every command):

1. the explicit value: the node's ``weights`` parameter (also from its ``--params-file``), a CLI's
   ``--weights``;
2. the ``PAIRVPR_WEIGHTS`` environment variable;
3. the ``weights`` entry of the parameter file a CLI is given (``--params-file``);
4. the per-user folder ``$XDG_DATA_HOME/pair_vpr_ros/`` (default ``~/.local/share/pair_vpr_ros/``)
   when it holds exactly one ``.pth``.

A value that is set but wrong (a missing file) is an error naming where it came from, never a
silent fall-through to the next place, and nothing falls back to the demo model. With no match at
all, one error names every place looked in and where to get the released checkpoints.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from pair_vpr_ros.errors import CheckpointError, ConfigError
from pair_vpr_ros.model import (
    ModelConfig,
    PairVPRModel,
    build_pairvpr,
    load_pairvpr,
    quantize_int8,
)
from pair_vpr_ros.model.devices import check_device
from pair_vpr_ros.model.threads import AUTO, apply_threads, check_threads, resolve_threads
from pair_vpr_ros.params.file import read_params_file

ENV_VAR = "PAIRVPR_WEIGHTS"
RANDOM_PREFIX = "random-"  # "random-<preset>": a randomly initialised network (tests, benchmarks)
RELEASED = (
    "get the authors' released checkpoints (pairvpr-vitB.pth, -vitL, -vitG) from the Pair-VPR "
    "repository (csiro-robotics/Pair-VPR on GitHub, or CSIRORobotics/Pair-VPR on Hugging Face), "
    "see docs/install.md, 'Released weights'"
)
PRECISIONS = ("fp32", "int8", "bf16", "fp16")
BACKENDS = ("torch", "openvino")  # torch: the reference; openvino: faster on a CPU (optional)
LOG = logging.getLogger("pair_vpr_ros.weights")


@dataclass(frozen=True)
class Weights:
    """Resolved weights: ``value`` is a checkpoint path or ``random-<preset>``; ``origin`` says
    where it was found (for messages)."""

    value: str
    origin: str


def user_weights_dir() -> Path:
    """``$XDG_DATA_HOME/pair_vpr_ros`` (an absolute XDG_DATA_HOME only, as the XDG spec says),
    else ``~/.local/share/pair_vpr_ros``."""
    base = os.environ.get("XDG_DATA_HOME", "")
    root = Path(base) if base and Path(base).is_absolute() else Path.home() / ".local" / "share"
    return root / "pair_vpr_ros"


def resolve_weights(
    explicit: str | os.PathLike | None = None,
    params_file: str | os.PathLike | None = None,
    *,
    explicit_name: str = "--weights",
    params_rule: bool = True,
) -> Weights:
    """Where the weights are, by the rules of this module's docstring. ``explicit_name`` names the
    explicit value in messages; ``params_rule`` False skips rule 3 (the node: ROS has put its
    parameter file into the ``weights`` parameter already). Raises ``CheckpointError`` when no
    place has any, or when the per-user folder holds several ``.pth``."""
    if explicit:
        return Weights(str(explicit), explicit_name)
    looked = [f"{explicit_name}: not given"]
    env = os.environ.get(ENV_VAR, "")
    if env:
        return Weights(env, f"${ENV_VAR}")
    looked.append(f"${ENV_VAR}: not set")
    if params_rule and params_file is not None:
        from_file = read_params_file(params_file)["weights"]
        if from_file:
            return Weights(str(from_file), f"'weights' in {params_file}")
        looked.append(f"'weights' in {params_file}: not set")
    elif params_rule:
        looked.append("'weights' in a --params-file: none given")
    folder = user_weights_dir()
    found = sorted(folder.glob("*.pth")) if folder.is_dir() else []
    if len(found) == 1:
        return Weights(str(found[0]), f"the one .pth in {folder}")
    if len(found) > 1:
        names = ", ".join(p.name for p in found)
        raise CheckpointError(
            f"{folder} holds {len(found)} .pth files ({names}): keep one there, or choose one "
            f"with {explicit_name} or ${ENV_VAR}"
        )
    looked.append(f"{folder}: {'no .pth file' if folder.is_dir() else 'no such folder'}")
    raise CheckpointError(
        f"no Pair-VPR weights found; looked in {'; '.join(looked)}. Set one of these to a "
        f"checkpoint (.pth) or put exactly one .pth into {folder}; {RELEASED}"
    )


def check_runtime(device: str | torch.device, precision: str, backend: str) -> torch.device:
    """Whether ``precision`` and ``backend`` can run on ``device`` (and the backend's optional
    packages are installed) -> the device; ``ConfigError`` saying what to change otherwise.
    Cheap: callers check before they read or write anything."""
    dev = check_device(device)
    if backend not in BACKENDS:
        raise ConfigError(f"backend {backend!r} must be one of {', '.join(BACKENDS)}")
    if precision not in PRECISIONS:
        raise ConfigError(f"precision {precision!r} must be one of {', '.join(PRECISIONS)}")
    if precision == "int8" and dev.type != "cpu":
        raise ConfigError("precision int8 runs on the CPU only: use device cpu, or bf16/fp16")
    if precision == "fp16" and dev.type != "cuda":
        raise ConfigError("precision fp16 needs a CUDA device: use device cuda, or bf16 on CPU")
    if backend == "openvino":
        if dev.type != "cpu":
            raise ConfigError(
                "backend openvino runs on the CPU only: use device cpu, or backend torch"
            )
        from pair_vpr_ros.model.openvino_backend import check_installed

        check_installed(precision)
    return dev


def load_model(
    weights: str | os.PathLike | Weights | None = None,
    *,
    device: str | torch.device = "cpu",
    precision: str = "fp32",
    image_size: int | None = None,
    params_file: str | os.PathLike | None = None,
    explicit_name: str = "--weights",
    params_rule: bool = True,
    backend: str = "torch",
    openvino_cache_dir: str | os.PathLike | None = "auto",
    openvino_calibration: Callable[[int], Tensor] | None = None,
    num_threads: int = AUTO,
) -> PairVPRModel:
    """The network to run -> ``PairVPR`` in eval mode on ``device`` (int8: a quantized CPU copy),
    or with ``backend`` openvino the same weights compiled by OpenVINO for the CPU
    (``OpenVINOModel``: fp32, bf16, or int8 calibrated on synthetic scenes, or on the images
    ``openvino_calibration`` returns for the model's image size, [B,3,S,S]:
    ``offline.bags.calibration.calibration_loader``), its converted graphs kept in
    ``openvino_cache_dir`` for the next start (``auto``: the per-user cache folder; '' or None:
    no cache; ``model/openvino_cache.py``).

    ``weights`` (else the other places: ``resolve_weights`` and its options; or what it
    returned) is a checkpoint path or ``random-<preset>`` (e.g. ``random-tiny``: a tiny random
    network, seed 0).
    ``num_threads`` (0: auto, by the model's size) sets the CPU threads of the whole process
    (``model.threads.apply_threads``): an explicit count before anything is loaded, auto as
    soon as the checkpoint says the size, before the network runs or OpenVINO compiles.
    ``image_size`` None or 0 keeps the checkpoint's. ``precision`` int8 quantizes here; bf16 /
    fp16 only need their device here (the caller runs the model under autocast). Raises
    ``CheckpointError`` (no, missing or unreadable weights, saying where they came from) or
    ``ConfigError`` (device, precision, preset).
    """
    found = weights
    if not isinstance(found, Weights):
        found = resolve_weights(
            weights, params_file, explicit_name=explicit_name, params_rule=params_rule
        )
    dev = check_runtime(device, precision, backend)
    if check_threads(num_threads) != AUTO:
        apply_threads(num_threads)
    if found.value.startswith(RANDOM_PREFIX):
        overrides = {"image_size": image_size} if image_size else {}
        config = ModelConfig.preset(found.value.removeprefix(RANDOM_PREFIX), **overrides)
        model = build_pairvpr(config, device=dev, seed=0)
    else:
        try:
            model = load_pairvpr(found.value, device=dev, image_size=image_size or None)
        except CheckpointError as err:
            raise CheckpointError(f"{err} (weights from {found.origin})") from err
    threads = resolve_threads(num_threads, model.config)
    if threads != num_threads:
        apply_threads(threads)
    if openvino_calibration is not None and (backend, precision) != ("openvino", "int8"):
        LOG.warning(
            "openvino_calibration is ignored: only backend openvino with precision int8 is "
            "calibrated (this is backend %s, precision %s)",
            backend,
            precision,
        )
    if backend == "openvino":
        from pair_vpr_ros.model.openvino_backend import OpenVINOModel  # optional dependency
        from pair_vpr_ros.model.openvino_cache import resolve_cache_dir

        calibration = None
        if openvino_calibration is not None and precision == "int8":
            calibration = openvino_calibration(model.config.image_size)
        cache_dir = resolve_cache_dir(openvino_cache_dir)
        return OpenVINOModel(
            model, precision, calibration=calibration, cache_dir=cache_dir, threads=threads
        )
    return quantize_int8(model) if precision == "int8" else model
