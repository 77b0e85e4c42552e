"""Optional int8 dynamic quantization of the Linear layers for CPU inference.

Weights are stored int8 per output channel; activations are quantized per batch on the fly. It
changes the numbers slightly: `benchmarks/bench_model.py` reports the agreement with fp32 (top-1
after re-ranking and descriptor cosine). The decoder embedding and the heads stay fp32: they
are cheap, and the descriptor and the logit are the outputs users threshold.
"""

from __future__ import annotations

import copy
import warnings

import torch
from torch import nn

from pair_vpr_ros.model.network import PairVPR


def quantize_int8(model: PairVPR) -> PairVPR:
    """A copy of `model` whose transformer-block Linears run int8 dynamic GEMMs (CPU only)."""
    qmodel = copy.deepcopy(model).cpu().eval()
    with warnings.catch_warnings():
        # torch.ao's eager quantization is deprecated in favour of torchao but is what ships here.
        warnings.simplefilter("ignore")
        from torch.ao.quantization import quantize_dynamic

        for blocks in (qmodel.encoder.model.blocks, qmodel.dec_blocks):
            quantize_dynamic(blocks, {nn.Linear}, dtype=torch.qint8, inplace=True)
    qmodel.weights_id = f"{model.weights_id}+int8"
    return qmodel
