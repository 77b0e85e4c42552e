"""Reading and writing Pair-VPR weights.

Accepted files: a released checkpoint (plain state_dict), `{"model": state_dict, ...}` (stage
one and our training checkpoints, nested any depth), keys with `module.` prefixes (DDP). Our own
files also store the architecture under `"arch"` (head counts cannot be read off shapes).
Files are always read with `weights_only=True`: a checkpoint can never run code.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import replace
from pathlib import Path

import torch
from torch import Tensor

from pair_vpr_ros.errors import CheckpointError, ConfigError
from pair_vpr_ros.hashing import sha256_file
from pair_vpr_ros.model.config import ModelConfig, shape_fields
from pair_vpr_ros.model.network import PairVPR, build_pairvpr

FORMAT = "pair_vpr_ros/1"
STAGE1_ONLY = ("mask_token", "prediction_head.weight", "prediction_head.bias")
# Missing from a stage-one checkpoint, new in stage two.
STAGE2_NEW = ("decoder_clstoken", "globalizer.", "classvprmodule.")


def read_checkpoint(path: str | os.PathLike) -> tuple[dict[str, Tensor], dict | None]:
    """-> (state_dict with `module.` prefixes removed, stored architecture dict or None)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(
            f"checkpoint {path} does not exist (or is not a file): pass the path of a Pair-VPR "
            "weights file such as pairvpr-vitB.pth (see docs/install.md, 'Released weights')"
        )
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for truncated or foreign files
        first = (str(err).splitlines() or ["no details"])[0][:200]  # EOFError('') when empty
        raise CheckpointError(
            f"checkpoint {path} could not be read as a PyTorch weights file "
            f"({type(err).__name__}: {first}); it may be empty, truncated or not a torch file "
            "(or it holds Python objects, which are never loaded): download it again"
        ) from err
    arch = None
    while isinstance(obj, dict) and isinstance(obj.get("model"), dict):
        arch = obj.get("arch", arch)
        obj = obj["model"]
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if (
        not isinstance(obj, dict)
        or not obj
        or not all(isinstance(v, Tensor) for v in obj.values())
    ):
        raise CheckpointError(
            f"checkpoint {path} holds a {type(obj).__name__}, not a state_dict of tensors: "
            "expected a Pair-VPR checkpoint (dict of parameter name -> tensor)"
        )
    return {_strip_module(k): v for k, v in obj.items()}, arch


def _strip_module(key: str) -> str:
    while key.startswith("module."):
        key = key[len("module.") :]
    return key


def config_for(sd: dict[str, Tensor], arch: dict | None, path: Path, image_size: int | None):
    """The architecture of a state_dict: the stored one, else read off the shapes."""
    if "encoder.model.cls_token" not in sd:
        hint = (
            "; it looks like a DINOv2 backbone: give it to pairvpr-train-stage1 --dinov2"
            if "cls_token" in sd and "blocks.0.norm1.weight" in sd
            else ""
        )
        raise CheckpointError(
            f"checkpoint {path} is not a Pair-VPR checkpoint: expected key "
            f"'encoder.model.cls_token', found keys like {sorted(sd)[:4]}{hint}"
        )
    try:
        seen = shape_fields(sd, image_size or 322)
        if arch is None:
            return ModelConfig.from_state_dict(sd, image_size=image_size or 322)
    except (KeyError, IndexError) as err:
        raise CheckpointError(
            f"checkpoint {path} lacks Pair-VPR parameter {err}: expected the encoder, "
            "`decoder_embed`, `dec_blocks.*` and `globalizer.0`"
        ) from err
    except (CheckpointError, ConfigError) as err:
        raise CheckpointError(f"checkpoint {path}: {err}") from err
    try:
        cfg = ModelConfig.from_dict(arch)
    except CheckpointError as err:
        raise CheckpointError(
            f"checkpoint {path}: {err}; its 'arch' entry is damaged or not from pair_vpr_ros"
        ) from err
    # The stored config says what shapes cannot (head counts); what shapes do say must agree,
    # or the loader would build a network (of any size) that cannot take these tensors.
    sources = {"dec_pos_grid": "dec_pos_embed", "desc_dim": "globalizer.0.weight"}
    sources["cls_hidden"] = "classvprmodule.0.weight"
    wrong = [
        f"{name}={getattr(cfg, name)} (tensors: {value})"
        for name, value in seen.items()
        if getattr(cfg, name) != value and sources.get(name, "encoder.model.cls_token") in sd
    ]
    if wrong:
        raise CheckpointError(
            f"checkpoint {path}: its stored architecture disagrees with its tensors: "
            f"{', '.join(wrong)}; the file is damaged"
        )
    return cfg if image_size is None else replace(cfg, image_size=image_size)


def load_pairvpr(
    path: str | os.PathLike | None,
    device: str | torch.device = "cpu",
    image_size: int | None = None,
    allow_missing: tuple[str, ...] = (),
    with_stage1_head: bool = False,
    config: ModelConfig | None = None,
) -> PairVPR:
    """Load a Pair-VPR checkpoint (strict: every parameter must be present and fit).

    With `path=None`, build a randomly initialised network from `config` (tests, training).

    `image_size` overrides the input size (default: stored, else 322). `allow_missing` names key
    prefixes that may be absent (e.g. `STAGE2_NEW` when starting stage two from stage one).
    Stage-one-only keys (`mask_token`, `prediction_head.*`) are ignored unless `with_stage1_head`.
    """
    if path is None:
        if config is None:
            raise CheckpointError("load_pairvpr needs a checkpoint path or a ModelConfig")
        return build_pairvpr(config, device)
    path = Path(path)
    sd, arch = read_checkpoint(path)
    cfg = config_for(sd, arch, path, image_size)
    has_head = "prediction_head.weight" in sd
    cfg = replace(cfg, with_stage1_head=with_stage1_head and has_head)
    model = PairVPR(cfg)
    if not cfg.with_stage1_head:
        sd = {k: v for k, v in sd.items() if k not in STAGE1_ONLY}
    _load_strict(model, sd, path, allow_missing)
    _check_finite(sd, path)
    model.weights_id = f"sha256:{sha256_file(path)[:16]}"
    return model.to(device).eval()


def _load_strict(model: PairVPR, sd: dict, path: Path, allow_missing: tuple[str, ...]) -> None:
    expected = model.state_dict()
    missing = [k for k in expected if k not in sd and not k.startswith(allow_missing)]
    unexpected = [k for k in sd if k not in expected]
    wrong = [
        f"{k}: expected {tuple(expected[k].shape)}, found {tuple(v.shape)}"
        for k, v in sd.items()
        if k in expected and v.shape != expected[k].shape
    ]
    if missing or unexpected or wrong:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing keys (e.g. {missing[:3]})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected keys (e.g. {unexpected[:3]})")
        if wrong:
            parts.append(f"{len(wrong)} shape mismatches (e.g. {wrong[:2]})")
        raise CheckpointError(
            f"checkpoint {path} does not fit the {model.config.arch} Pair-VPR network: "
            + "; ".join(parts)
            + ". Is it a complete Pair-VPR checkpoint (pairvpr-vitB/L/G.pth or one of ours)?"
        )
    model.load_state_dict(sd, strict=not allow_missing)


def _check_finite(sd: dict[str, Tensor], path: Path) -> None:
    """NaN/inf weights (a diverged run, a damaged file) would only show up as non-finite
    descriptors at the first frame: refuse them when loading instead."""
    bad = [k for k, v in sd.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise CheckpointError(
            f"checkpoint {path} holds NaN or infinite values in {len(bad)} of {len(sd)} "
            f"tensors (e.g. {bad[:3]}): it is damaged or comes from a training run that "
            "diverged; use another checkpoint (for training: an earlier one)"
        )


def load_dinov2_encoder(model: PairVPR, path: str | os.PathLike) -> list[str]:
    """Copy DINOv2 `*_reg4_pretrain.pth` backbone weights into `model.encoder.model`.

    Returns the names of encoder parameters the file did not provide (none for a matching file).
    """
    path = Path(path)
    sd, _ = read_checkpoint(path)
    # Chunked giant checkpoints name blocks `blocks.<chunk>.<i>.`: drop the chunk level.
    sd = {_unchunk(k): v for k, v in sd.items()}
    target = model.encoder.model.state_dict()
    if "cls_token" not in sd or "blocks.0.norm1.weight" not in sd:
        raise CheckpointError(
            f"{path} is not a DINOv2 backbone: expected keys 'cls_token' and 'blocks.N.*', "
            f"found keys like {sorted(sd)[:4]}"
        )
    depth = len({k.split(".")[1] for k in sd if k.startswith("blocks.")})
    found, want = (sd["cls_token"].shape[-1], depth), (model.config.embed_dim, model.config.depth)
    if found != want or "register_tokens" not in sd:
        raise CheckpointError(
            f"DINOv2 weights {path} are D={found[0]} with {found[1]} blocks"
            f"{'' if 'register_tokens' in sd else ' without register tokens'}, but the model's "
            f"encoder is D={want[0]} with {want[1]} blocks and 4 registers: use the matching "
            "dinov2_vit*14_reg4_pretrain.pth"
        )
    usable = {k: v for k, v in sd.items() if k in target and v.shape == target[k].shape}
    model.encoder.model.load_state_dict(usable, strict=False)
    return sorted(set(target) - set(usable))


def _unchunk(key: str) -> str:
    parts = key.split(".")
    if len(parts) > 3 and parts[0] == "blocks" and parts[1].isdigit() and parts[2].isdigit():
        return ".".join([parts[0], *parts[2:]])
    return key


def save_pairvpr(model: PairVPR, path: str | os.PathLike, extra: dict | None = None) -> Path:
    """Write `{"model": state_dict, "arch": config, "format": ...}` atomically (temp + rename)."""
    payload = {"model": model.state_dict(), "arch": model.config.to_dict(), "format": FORMAT}
    payload.update(extra or {})
    return _save_atomic(payload, Path(path))


def save_encoder_backbone(model: PairVPR, path: str | os.PathLike) -> Path:
    """Write the encoder alone with DINOv2's key names (`cls_token`, `blocks.N.*`, ...), so that
    `load_dinov2_encoder` and the trainers' `--dinov2` take it: an encoder we trained ourselves
    can then stand in for DINOv2 (the demo model's 128-d encoder has no DINOv2 counterpart)."""
    state = {k: v.detach().clone() for k, v in model.encoder.model.state_dict().items()}
    return _save_atomic(state, Path(path))


def _save_atomic(payload: dict, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        torch.save(payload, tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
