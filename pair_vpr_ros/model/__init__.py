"""The Pair-VPR network (ROS-free): encoder, global head, pair classifier, loading and input."""

from pair_vpr_ros.model.checkpoint import (
    load_dinov2_encoder,
    load_pairvpr,
    save_encoder_backbone,
    save_pairvpr,
)
from pair_vpr_ros.model.config import ModelConfig
from pair_vpr_ros.model.interface import PairVPRModel
from pair_vpr_ros.model.network import PairVPR, build_pairvpr
from pair_vpr_ros.model.preprocess import preprocess, preprocess_batch
from pair_vpr_ros.model.quantize import quantize_int8

__all__ = [
    "ModelConfig",
    "PairVPR",
    "PairVPRModel",
    "build_pairvpr",
    "load_dinov2_encoder",
    "load_pairvpr",
    "preprocess",
    "preprocess_batch",
    "quantize_int8",
    "save_encoder_backbone",
    "save_pairvpr",
]
