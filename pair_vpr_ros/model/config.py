"""Architecture of a Pair-VPR network: encoder size, decoder, heads, input size.

Released checkpoints carry no config, so `ModelConfig.from_state_dict` reads one off the
tensor shapes (head counts are not visible in shapes: the released models use 64-d heads
throughout). Our own checkpoints store the config beside the tensors (see `checkpoint.py`).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, fields, replace

from ..errors import CheckpointError, ConfigError

PATCH = 14
HEAD_DIM = 64


@dataclass(frozen=True)
class ModelConfig:
    """Every number that shapes the network. Defaults are the released ViT-B model at 322 px."""

    arch: str = "B"
    embed_dim: int = 768  # encoder width D
    depth: int = 12
    num_heads: int = 12
    mlp_hidden: int = 3072  # 4D for fc1/fc2, 4096 for the SwiGLU of ViT-G
    swiglu: bool = False
    num_registers: int = 4
    pos_grid: int = 37  # the encoder's position grid was trained at 518 px
    dec_dim: int = 768
    dec_depth: int = 12
    dec_heads: int = 12
    dec_mlp_hidden: int = 3072
    dec_qkv_bias: bool = True
    dec_pos_grid: int = 23  # grid of the stored decoder position tables (322 px)
    desc_dim: int = 512
    cls_hidden: int = 512
    image_size: int = 322
    with_stage1_head: bool = False  # `mask_token` + `prediction_head` for stage-one training

    def __post_init__(self) -> None:
        if self.image_size <= 0 or self.image_size % PATCH:
            raise ConfigError(
                f"image_size={self.image_size} is not a positive multiple of {PATCH}: "
                "use e.g. 224, 322 or 518"
            )
        for name, width, heads in (
            ("encoder", self.embed_dim, self.num_heads),
            ("decoder", self.dec_dim, self.dec_heads),
        ):
            if heads <= 0 or width % heads:
                raise ConfigError(f"{name} width {width} is not divisible by {heads} heads")

    @property
    def grid(self) -> int:
        """Patch rows (= columns) at `image_size`."""
        return self.image_size // PATCH

    @property
    def num_patches(self) -> int:
        return self.grid * self.grid

    # ---- presets -------------------------------------------------------------------------
    @classmethod
    def preset(cls, name: str, **overrides) -> ModelConfig:
        """`S`, `B`, `L`, `G` (the paper's encoders, 768-d 12-block decoder), `small` and `tiny`
        (CPU-sized models for the demo and tests: same code paths, fewer and narrower layers)."""
        key = name.upper() if name.upper() in _PRESETS else name.lower()
        if key not in _PRESETS:
            raise ConfigError(
                f"unknown model preset {name!r}: choose one of {', '.join(_PRESETS)}"
            )
        return replace(cls(), arch=key, **{**_PRESETS[key], **overrides})

    @classmethod
    def tiny(cls, **overrides) -> ModelConfig:
        return cls.preset("tiny", **overrides)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> ModelConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise CheckpointError(f"stored model config has unknown fields {unknown}")
        return cls(**data)

    @classmethod
    def from_state_dict(cls, sd: dict, image_size: int = 322) -> ModelConfig:
        """Read the architecture off a released checkpoint's tensor shapes ([see module doc])."""
        d = sd["encoder.model.cls_token"].shape[-1]
        depth = _count_prefix(sd, r"encoder\.model\.blocks\.(\d+)\.")
        swiglu = "encoder.model.blocks.0.mlp.w12.weight" in sd
        hidden = (
            sd["encoder.model.blocks.0.mlp.w3.weight"].shape[1]
            if swiglu
            else sd["encoder.model.blocks.0.mlp.fc1.weight"].shape[0]
        )
        pos_tokens = sd["encoder.model.pos_embed"].shape[1] - 1
        dec_dim = sd["decoder_embed.weight"].shape[0]
        dec_tokens = sd["dec_pos_embed"].shape[0] if "dec_pos_embed" in sd else None
        arch = {384: "S", 768: "B", 1024: "L", 1536: "G"}.get(d, f"custom-{d}")
        return cls(
            arch=arch,
            embed_dim=d,
            depth=depth,
            num_heads=d // HEAD_DIM,
            mlp_hidden=hidden,
            swiglu=swiglu,
            num_registers=sd["encoder.model.register_tokens"].shape[1],
            pos_grid=_square_side(pos_tokens, "encoder.model.pos_embed"),
            dec_dim=dec_dim,
            dec_depth=_count_prefix(sd, r"dec_blocks\.(\d+)\."),
            dec_heads=dec_dim // HEAD_DIM,
            dec_mlp_hidden=sd["dec_blocks.0.mlp.fc1.weight"].shape[0],
            dec_qkv_bias="dec_blocks.0.cross_attn.projq.bias" in sd,
            dec_pos_grid=(
                _square_side(dec_tokens, "dec_pos_embed") if dec_tokens else image_size // PATCH
            ),
            desc_dim=sd["globalizer.0.weight"].shape[0] if "globalizer.0.weight" in sd else 512,
            cls_hidden=(
                sd["classvprmodule.0.weight"].shape[0] if "classvprmodule.0.weight" in sd else 512
            ),
            image_size=image_size,
        )


_ENC = {
    "S": dict(embed_dim=384, depth=12, num_heads=6, mlp_hidden=1536),
    "B": dict(embed_dim=768, depth=12, num_heads=12, mlp_hidden=3072),
    "L": dict(embed_dim=1024, depth=24, num_heads=16, mlp_hidden=4096),
    "G": dict(embed_dim=1536, depth=40, num_heads=24, mlp_hidden=4096, swiglu=True),
}
_PRESETS: dict[str, dict] = {
    **_ENC,
    # Small models of our own: same parameter names and code paths, sized for a laptop CPU.
    "small": dict(  # the demo model: ~1.45 M parameters, 2.9 MB in float16
        embed_dim=128,
        depth=4,
        num_heads=2,
        mlp_hidden=512,
        pos_grid=8,
        dec_dim=128,
        dec_depth=2,
        dec_heads=2,
        dec_mlp_hidden=512,
        dec_pos_grid=8,
        cls_hidden=128,
        image_size=112,
    ),
    "tiny": dict(
        embed_dim=32,
        depth=2,
        num_heads=2,
        mlp_hidden=64,
        pos_grid=4,
        dec_dim=32,
        dec_depth=2,
        dec_heads=2,
        dec_mlp_hidden=64,
        dec_pos_grid=4,
        cls_hidden=16,
        image_size=56,
    ),
}


def _count_prefix(sd: dict, pattern: str) -> int:
    rx = re.compile(pattern)
    idx = {int(m.group(1)) for k in sd if (m := rx.match(k))}
    if not idx:
        raise CheckpointError(f"no parameters match {pattern!r}")
    return max(idx) + 1


def _square_side(tokens: int, name: str) -> int:
    side = int(round(tokens**0.5))
    if side * side != tokens:
        raise CheckpointError(f"{name} holds {tokens} position rows, not a square grid")
    return side
