"""The Pair-VPR network (ROS-free): encoder, global head, pair classifier, loading and input."""

from .checkpoint import load_dinov2_encoder, load_pairvpr, save_encoder_backbone, save_pairvpr
from .config import ModelConfig
from .network import PairVPR, build_pairvpr
from .preprocess import preprocess, preprocess_batch
from .quantize import quantize_int8

__all__ = [
    "ModelConfig",
    "PairVPR",
    "build_pairvpr",
    "load_dinov2_encoder",
    "load_pairvpr",
    "preprocess",
    "preprocess_batch",
    "quantize_int8",
    "save_encoder_backbone",
    "save_pairvpr",
]
