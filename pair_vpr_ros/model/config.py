"""Architecture of a Pair-VPR network: encoder size, decoder, heads, input size.

Released checkpoints carry no config, so `ModelConfig.from_state_dict` reads one off the
tensor shapes (head counts are not visible in shapes: the released models use 64-d heads
throughout). Our own checkpoints store the config beside the tensors (see `checkpoint.py`).
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, fields, replace

from pair_vpr_ros.errors import CheckpointError, ConfigError

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
        """A stored config (`to_dict`); CheckpointError for unknown fields or wrong types."""
        if not isinstance(data, dict):
            raise CheckpointError(
                f"stored model config is a {type(data).__name__}, not a dict of ModelConfig fields"
            )
        types = {f.name: type(f.default) for f in fields(cls)}
        unknown = sorted(str(k) for k in set(data) - set(types))
        if unknown:
            raise CheckpointError(f"stored model config has unknown fields {unknown}")
        for name, value in data.items():
            kind = types[name]
            if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise CheckpointError(
                    f"stored model config field {name}={value!r} is not {kind.__name__}"
                )
        try:
            return cls(**data)
        except ConfigError as err:
            raise CheckpointError(f"stored model config is invalid: {err}") from err

    @classmethod
    def from_state_dict(cls, sd: dict, image_size: int = 322) -> ModelConfig:
        """Read the architecture off a released checkpoint's tensor shapes ([see module doc])."""
        seen = shape_fields(sd, image_size)
        d, dec_dim = seen["embed_dim"], seen["dec_dim"]
        return cls(
            arch={384: "S", 768: "B", 1024: "L", 1536: "G"}.get(d, f"custom-{d}"),
            num_heads=d // HEAD_DIM,
            dec_heads=dec_dim // HEAD_DIM,
            image_size=image_size,
            **seen,
        )


def shape_fields(sd: dict, image_size: int = 322) -> dict:
    """The ModelConfig fields a state_dict's shapes show (all but arch, heads, image size).

    KeyError names a missing tensor. desc_dim, cls_hidden and dec_pos_grid fall back to the
    released values (or `image_size`) when their tensor is absent (stage-one checkpoints).
    """
    swiglu = "encoder.model.blocks.0.mlp.w12.weight" in sd
    dec_tokens = sd["dec_pos_embed"].shape[0] if "dec_pos_embed" in sd else None
    return dict(
        embed_dim=sd["encoder.model.cls_token"].shape[-1],
        depth=_count_prefix(sd, r"encoder\.model\.blocks\.(\d+)\."),
        mlp_hidden=(
            sd["encoder.model.blocks.0.mlp.w3.weight"].shape[1]
            if swiglu
            else sd["encoder.model.blocks.0.mlp.fc1.weight"].shape[0]
        ),
        swiglu=swiglu,
        num_registers=sd["encoder.model.register_tokens"].shape[1],
        pos_grid=_square_side(
            sd["encoder.model.pos_embed"].shape[1] - 1, "encoder.model.pos_embed"
        ),
        dec_dim=sd["decoder_embed.weight"].shape[0],
        dec_depth=_count_prefix(sd, r"dec_blocks\.(\d+)\."),
        dec_mlp_hidden=sd["dec_blocks.0.mlp.fc1.weight"].shape[0],
        dec_qkv_bias="dec_blocks.0.cross_attn.projq.bias" in sd,
        dec_pos_grid=(
            _square_side(dec_tokens, "dec_pos_embed") if dec_tokens else image_size // PATCH
        ),
        desc_dim=sd["globalizer.0.weight"].shape[0] if "globalizer.0.weight" in sd else 512,
        cls_hidden=(
            sd["classvprmodule.0.weight"].shape[0] if "classvprmodule.0.weight" in sd else 512
        ),
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
    """Number of blocks matching `pattern` (numbered 0..n-1; a gap is an error, so a stray key
    like `blocks.99999.x` cannot make the loader build 100000 blocks)."""
    rx = re.compile(pattern)
    idx = {int(m.group(1)) for k in sd if (m := rx.match(k))}
    if not idx:
        raise CheckpointError(f"no parameters match {pattern!r}")
    if len(idx) != max(idx) + 1:
        missing = sorted(set(range(max(idx) + 1)) - idx)
        raise CheckpointError(
            f"blocks matching {pattern!r} are numbered up to {max(idx)} but {len(missing)} are "
            f"missing (e.g. {missing[:3]})"
        )
    return max(idx) + 1


def _square_side(tokens: int, name: str) -> int:
    side = int(round(tokens**0.5))
    if side * side != tokens:
        raise CheckpointError(f"{name} holds {tokens} position rows, not a square grid")
    return side
