"""OpenVINO back end (`backend: openvino`): the network compiled by OpenVINO for the CPU.

Chosen over ONNX Runtime by measurement (docs/performance.md, "Faster CPU back end").
The graphs come from our own modules (`export.py`); `precision` picks what OpenVINO runs:
- fp32: f32 kernels throughout (agrees with torch to float rounding);
- bf16: OpenVINO's default on a CPU with bf16 instructions (f32 elsewhere);
- int8: static int8 from NNCF (symmetric, per-tensor activations whose ranges are the min/max
  seen on synthetic scenes from `calibration.py` or on images the caller passes, such as the
  user's own bag or image folder, `offline/bags/calibration.py`; per-channel weights); the
  float layers run in f32.

`OpenVINOModel` implements `PairVPRModel`, so the pipeline, map and replay run it unchanged.
OpenVINO and NNCF are optional (`pip install 'pair_vpr_ros[openvino]'`).
"""

from __future__ import annotations

import importlib
import importlib.util
import os
from pathlib import Path
from types import ModuleType

import numpy as np
import torch
from torch import Tensor

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.model.calibration import CALIBRATION_IMAGES, synthetic_calibration
from pair_vpr_ros.model.config import ModelConfig
from pair_vpr_ros.model.export import (
    ONE_WAY,
    ONE_WAY_CHUNK,
    Graphs,
    example_inputs,
    export_graphs,
)
from pair_vpr_ros.model.network import PairVPR, fingerprint
from pair_vpr_ros.model.openvino_cache import CacheEntry, entry_parts, shared_core

PRECISIONS = ("fp32", "bf16", "int8")
PACKAGES = {"fp32": ("openvino",), "bf16": ("openvino",), "int8": ("openvino", "nncf")}


def _not_installed(module: str) -> ConfigError:
    return ConfigError(
        f"backend openvino needs the package {module!r}, which is not installed: pip install "
        "'pair_vpr_ros[openvino]' (make setup installs it), or use backend torch"
    )


def check_installed(precision: str) -> None:
    """ConfigError when a package `precision` needs is missing (found without importing it)."""
    for module in PACKAGES.get(precision, ()):
        if importlib.util.find_spec(module) is None:
            raise _not_installed(module)


def require(module: str) -> ModuleType:
    """Import an optional dependency of this back end, or say how to get it."""
    try:
        return importlib.import_module(module)
    except ImportError as err:
        raise _not_installed(module) from err


class OpenVINOModel:
    """`PairVPRModel` on OpenVINO: encode one image per inference, re-rank `chunk_size`
    candidates per inference (the last chunk padded), both directions or, for the re-rank
    cascade (`query_scorer`), one."""

    def __init__(
        self,
        model: PairVPR,
        precision: str = "fp32",
        calibration: Tensor | None = None,
        chunk: int = 2,
        cache_dir: str | os.PathLike | None = None,
        threads: int | None = None,
    ) -> None:
        """`model`: the torch network to compile; `calibration` [B,3,S,S] preprocessed images for
        int8 (default: `CALIBRATION_IMAGES` synthetic scenes); `cache_dir`: a folder that keeps
        the converted (int8: quantized) graphs for the next start (`openvino_cache.py`; None:
        no cache). `from_cache` says whether they came from there. `threads`: inference threads
        (None: torch's count, which `threads.apply_threads` sets), in one stream."""
        if precision not in PRECISIONS:
            raise ConfigError(
                f"backend openvino runs precision {', '.join(PRECISIONS)}, not {precision!r}"
            )
        if calibration is not None and calibration.shape[0] < 2:
            raise ConfigError("int8 calibration needs at least 2 images")
        ov = require("openvino")
        self._config: ModelConfig = model.config
        suffix = "+ov-int8" if precision == "int8" else ""  # int8 descriptors differ slightly
        self._fingerprint = fingerprint(model.weights_id + suffix, model.config)
        self.precision = precision
        self.chunk_size = chunk
        if precision == "int8" and calibration is None:
            calibration = synthetic_calibration(CALIBRATION_IMAGES, model.config.image_size)
        self.from_cache = False
        self.cache_path: Path | None = None
        converted = self._graphs(ov, model, calibration, cache_dir)
        # int8 runs its float layers in f32: as fast as in bf16 here (0.18x vs 0.19x encode),
        # and the logits do not get bf16's 8-bit mantissa.
        hint = {"INFERENCE_PRECISION_HINT": "f32"} if precision != "bf16" else {}
        # One stream: the pipeline runs one request at a time, so more streams only split the
        # threads between requests that never come.
        threads = threads or torch.get_num_threads()
        config = {**hint, "INFERENCE_NUM_THREADS": threads, "NUM_STREAMS": 1}
        core = shared_core(ov)
        self._requests = {
            name: core.compile_model(graph, "CPU", config).create_infer_request()
            for name, graph in converted.items()
        }

    def _graphs(
        self, ov: ModuleType, model: PairVPR, calibration: Tensor | None, cache_dir
    ) -> dict:
        """The OpenVINO graphs to compile: from the cache entry when it has them, else built
        (and stored there)."""
        entry, shapes = None, {}
        if cache_dir is not None:
            parts = entry_parts(model, self.precision, self.chunk_size, calibration)
            entry = CacheEntry(cache_dir, parts)
            self.cache_path = entry.path
            shapes = {
                name: [tuple(x.shape) for x in inputs]
                for name, inputs in example_inputs(model, self.chunk_size).items()
            }
            converted = entry.load(ov, shapes)
            if converted is not None:
                self.from_cache = True
                return converted
        converted = build_graphs(ov, model, self.chunk_size)
        if self.precision == "int8":
            converted = quantize(converted, model, calibration, self.chunk_size)
        if entry is not None and entry.save(ov, converted):
            # Compile what later starts will read: the first start then computes the same bits
            # (a graph read back from IR compiles to kernels that differ by ~1e-8).
            converted = entry.load(ov, shapes) or converted
        return converted

    # ---- PairVPRModel --------------------------------------------------------------------
    @property
    def config(self) -> ModelConfig:
        return self._config

    @property
    def fingerprint(self) -> str:
        return self._fingerprint

    @property
    def num_patches(self) -> int:
        return self._config.num_patches

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")

    @property
    def dense_dtype(self) -> torch.dtype:
        return torch.float32

    def encode(self, images: Tensor) -> tuple[Tensor, Tensor]:
        """images [B,3,S,S] -> (dense [B,N,D], descriptors [B,desc_dim]), one image at a time."""
        size = self._config.image_size
        if images.ndim != 4 or tuple(images.shape[1:]) != (3, size, size):
            raise ConfigError(
                f"backend openvino was compiled for images [B,3,{size},{size}], got "
                f"{list(images.shape)}: preprocess to the model's image_size"
            )
        outs = [self._run("encoder", image[None]) for image in images.float()]
        return tuple(torch.cat([o[i] for o in outs]) for i in range(2))  # type: ignore[return-value]

    def pair_scores(self, query: Tensor, cands: Tensor, chunk: int | None = None) -> Tensor:
        """query [N,D], cands [K,N,D] -> logit(q,c) + logit(c,q) [K]. `chunk` is ignored: the
        graph was compiled for `chunk_size` candidates per call."""
        if cands.shape[0] == 0:
            return torch.zeros(0)
        return self.query_scorer(query).scores(cands)

    def query_scorer(self, query: Tensor, chunk: int | None = None) -> OpenVINOQueryScorer:
        """The query [N,D]'s side (the "query" graph) run once, for any number of calls."""
        return OpenVINOQueryScorer(self, self._run("query", query.float()))

    def run_chunks(self, name: str, query_side: list[Tensor], cands: Tensor) -> Tensor:
        """The chunk graph `name` over cands [K,N,D], as many at a time as it was compiled for
        (`chunk_size`; the one-direction graphs `ONE_WAY_CHUNK`) -> [K]."""
        size = ONE_WAY_CHUNK if name in ONE_WAY else self.chunk_size
        out = []
        for i in range(0, cands.shape[0], size):
            part = cands[i : i + size].float()
            short = size - part.shape[0]
            if short:  # pad with copies of the last candidate; their scores are dropped
                part = torch.cat([part, part[-1:].expand(short, -1, -1)])
            scores = self._run(name, *query_side, part)[0]
            out.append(scores[: size - short])
        return torch.cat(out) if out else torch.zeros(0)

    def _run(self, name: str, *inputs: Tensor) -> list[Tensor]:
        request = self._requests[name]
        request.infer([np.ascontiguousarray(x.detach().cpu().numpy()) for x in inputs])
        return [torch.from_numpy(out.data.copy()) for out in request.output_tensors]


class OpenVINOQueryScorer:
    """One query's re-ranking on OpenVINO (`PairClassifier.query_scorer`'s counterpart)."""

    def __init__(self, model: OpenVINOModel, query_side: list[Tensor]) -> None:
        self.model, self.query_side = model, query_side

    def scores(self, cands: Tensor) -> Tensor:
        """cands [K,N,D] -> logit(q,c) + logit(c,q) [K] (the "chunk" graph)."""
        return self.model.run_chunks("chunk", self.query_side, cands)

    def logits(self, cands: Tensor, first: str) -> Tensor:
        """cands [K,N,D] -> one direction's logits [K]: `first` "query" or "candidate"."""
        for name, (graph_first, inputs) in ONE_WAY.items():
            if graph_first == first:
                side = [self.query_side[i] for i in inputs]
                return self.model.run_chunks(name, side, cands)
        raise ValueError(f"first must be 'query' or 'candidate', got {first!r}")


def build_graphs(ov: ModuleType, model: PairVPR, chunk: int) -> dict:
    """The network as OpenVINO graphs {"encoder", "query", "chunk", "chunk_query",
    "chunk_candidate"}, float: exported with `torch.export`, then converted (the slow part of a
    start without a cache entry)."""
    return convert(ov, export_graphs(model, chunk), model)


def convert(ov: ModuleType, graphs: Graphs, model: PairVPR) -> dict:
    """Exported programs -> OpenVINO models with their inputs fixed to the exported shapes."""
    inputs = example_inputs(model, graphs.chunk_size)
    out = {}
    for name in ("encoder", "query", "chunk", *ONE_WAY):
        if getattr(graphs, name) is None:
            continue
        graph = ov.convert_model(getattr(graphs, name))
        shapes = [ov.PartialShape(list(x.shape)) for x in inputs[name]]
        graph.reshape(dict(zip(graph.inputs, shapes, strict=True)))
        out[name] = graph
    return out


def quantize(converted: dict, model: PairVPR, images: Tensor, chunk: int) -> dict:
    """Static int8 (NNCF) of the encoder and the re-rank chunks; activation ranges from `images`
    [B,3,S,S] and, for re-ranking, pairs of their dense tokens (the same pairs for the
    two-direction chunk and the one-direction ones). The per-query graph runs once per query
    and stays as it is."""
    nncf = require("nncf")
    with torch.no_grad():
        dense = torch.cat([model.encode(images[i : i + 1])[0] for i in range(len(images))])
        pairs = []
        for i in range(max(1, len(images) // 2)):
            x_query, memory = model.query_side(dense[i])
            keys, values = (torch.stack(t).numpy() for t in zip(*memory, strict=True))
            others = [(i + 1 + j) % len(images) for j in range(chunk)]
            pairs.append((x_query.numpy(), keys, values, dense[others].numpy()))
    samples = {"encoder": [images[i : i + 1].numpy() for i in range(len(images))]}
    samples["chunk"] = pairs
    for name, (_, inputs) in ONE_WAY.items():  # the same pairs, the inputs each graph takes
        if name in converted:
            samples[name] = [
                (*(p[i] for i in inputs), p[3][j : j + ONE_WAY_CHUNK])
                for p in pairs
                for j in range(0, len(p[3]), ONE_WAY_CHUNK)
            ]
    out = dict(converted)
    for name, data in samples.items():
        out[name] = nncf.quantize(
            converted[name],
            nncf.Dataset(data),
            model_type=nncf.ModelType.TRANSFORMER,
            preset=nncf.QuantizationPreset.PERFORMANCE,
            subset_size=len(data),
            ignored_scope=nncf.IgnoredScope(names=head_layers(converted[name], name)),
            advanced_parameters=advanced_parameters(nncf),
        )
    return out


def advanced_parameters(nncf: ModuleType) -> object:
    """NNCF settings chosen by measurement (2026-11-24; mean descriptor cosine with torch fp32,
    demo model on 100 demo-world images / ViT-B random weights on 8): NNCF's defaults for
    transformers (asymmetric activations, outlier-clipping range estimate) 0.99864 / 0.99873;
    symmetric activations (`PERFORMANCE` preset) 0.99907 / -; plus activation ranges from the
    calibration minimum and maximum 0.99957 / 0.99936, at the same speed. SmoothQuant, NNCF's
    default for transformers, stays off: it lowered the demo model's cosine to 0.986-0.995.
    The overflow fix (weights in 7 bits) is on for every layer: CPUs without VNNI (AVX2 only,
    e.g. the AMD EPYC CI machine of 2026-11-27) multiply u8 x s8 into saturating 16-bit sums,
    and without it the tiny test network's pair scores were off by 0.29 there (0.15 allowed);
    VNNI CPUs lose at most a bit of weight resolution."""
    estimators = importlib.import_module("nncf.quantization.range_estimator")
    advanced = importlib.import_module("nncf.quantization.advanced_parameters")
    return nncf.AdvancedQuantizationParameters(
        overflow_fix=advanced.OverflowFix.ENABLE,
        smooth_quant_alphas=nncf.AdvancedSmoothQuantParameters(matmul=-1, convolution=-1),
        activations_range_estimator_params=estimators.RangeEstimatorParametersSet.MINMAX,
    )


def head_layers(graph, name: str) -> list[str]:
    """The layers int8 leaves in float, as torch int8 does: the encoder's patch embedding and
    global head, the re-rank's decoder embedding and pair classifier. They are cheap, and the
    descriptor and the logit are what users threshold. Found by position (first and last
    weighted layers in topological order; every re-rank chunk starts with the decoder embedding
    and ends with the classifier), since exported names are generic."""
    ops = [op for op in graph.get_ordered_ops() if op.get_type_name() in ("MatMul", "Convolution")]
    names = [op.get_friendly_name() for op in ops]
    return names[:1] + names[-1:] if name == "encoder" else names[:1] + names[-2:]
