"""The OpenVINO back end: the exported graphs compute what torch computes (tiny model), it plugs
in as a `PairVPRModel`, int8 stays close. Skipped without the optional packages."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from extras import require

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.loops.scoring import encode_for_map
from pair_vpr_ros.model import ModelConfig, PairVPRModel, build_pairvpr
from pair_vpr_ros.model.calibration import synthetic_calibration, synthetic_scene
from pair_vpr_ros.model.export import example_inputs, export_graphs
from pair_vpr_ros.weights import load_model

require("openvino")
from pair_vpr_ros.model.openvino_backend import OpenVINOModel  # noqa: E402

K = 5  # three chunks of 2: the last one padded


@pytest.fixture(scope="module")
def torch_model():
    return build_pairvpr(ModelConfig.tiny(), seed=0)


@pytest.fixture(scope="module")
def inputs(torch_model):
    images = synthetic_calibration(K + 1, torch_model.config.image_size, seed=100)
    with torch.inference_mode():
        dense, desc = torch_model.encode(images)
    return images, dense, desc


@pytest.fixture(scope="module")
def ov_fp32(torch_model):
    """The node's way: `load_model` with backend openvino (random-tiny is `torch_model`)."""
    return load_model("random-tiny", backend="openvino")


def test_exported_programs_run_our_modules(torch_model, inputs):
    images, dense, desc = inputs
    graphs = export_graphs(torch_model, chunk=2)
    with torch.inference_mode():
        got_dense, got_desc = graphs.encoder.module()(images[:1])
        x_query, keys, values = graphs.query.module()(dense[0])
        scores = graphs.chunk.module()(x_query, keys, values, dense[1:3])
        want = torch_model.pair_scores(dense[0], dense[1:3])
    torch.testing.assert_close(got_dense, dense[:1], rtol=0, atol=1e-5)
    torch.testing.assert_close(got_desc, desc[:1], rtol=0, atol=1e-6)
    torch.testing.assert_close(scores, want, rtol=0, atol=1e-5)
    shapes = [tuple(x.shape) for x in example_inputs(torch_model, 2)["chunk"]]
    memory = (2, 1, 2, 16, 16)  # [blocks, 1, heads, N, head dim]
    assert shapes == [(1, 17, 32), memory, memory, (2, 16, 32)]


def test_fp32_agrees_with_torch(torch_model, inputs, ov_fp32):
    images, dense, desc = inputs
    assert isinstance(ov_fp32, OpenVINOModel) and isinstance(ov_fp32, PairVPRModel)
    assert ov_fp32.precision == "fp32"
    assert ov_fp32.fingerprint == torch_model.fingerprint  # same descriptors: maps are shared
    assert (ov_fp32.num_patches, ov_fp32.dense_dtype) == (16, torch.float32)
    got_dense, got_desc = ov_fp32.encode(images)
    torch.testing.assert_close(got_dense, dense, rtol=0, atol=1e-5)
    torch.testing.assert_close(got_desc, desc, rtol=0, atol=1e-6)
    with torch.inference_mode():
        want = torch_model.pair_scores(dense[0], dense[1:])
        reference = torch_model.pair_scores_reference(dense[0], dense[1:])
    got = ov_fp32.pair_scores(dense[0], dense[1:])
    assert got.shape == (K,)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-5)
    torch.testing.assert_close(got, reference, rtol=0, atol=1e-5)
    assert ov_fp32.pair_scores(dense[0], dense[1:1]).shape == (0,)
    # the re-rank cascade's one-direction graphs (3 candidates: one padded chunk)
    scorer, q = ov_fp32.query_scorer(dense[0]), dense[0][None].expand(3, -1, -1)
    with torch.inference_mode():
        want_qc = torch_model.pair_logits(q, dense[1:4], fast=False)
        want_cq = torch_model.pair_logits(dense[1:4], q, fast=False)
    torch.testing.assert_close(scorer.logits(dense[1:4], "query"), want_qc, rtol=0, atol=1e-5)
    torch.testing.assert_close(scorer.logits(dense[1:4], "candidate"), want_cq, rtol=0, atol=1e-5)
    torch.testing.assert_close(scorer.scores(dense[1:4]), want[:3], rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="first must be 'query' or 'candidate', got 'both'"):
        scorer.logits(dense[1:4], "both")


def test_the_pipeline_stores_what_torch_stores(torch_model, inputs, ov_fp32):
    images = inputs[0]
    got_dense, got_desc = encode_for_map(ov_fp32, images)
    want_dense, want_desc = encode_for_map(torch_model, images)
    assert got_dense.dtype == np.float16 and got_dense.shape == want_dense.shape
    np.testing.assert_allclose(got_dense, want_dense, rtol=0, atol=2e-3)
    np.testing.assert_allclose(got_desc, want_desc, rtol=0, atol=1e-6)


def test_compiled_with_the_process_threads_in_one_stream(ov_fp32):
    compiled = ov_fp32._requests["encoder"].get_compiled_model()
    # random-tiny is a light network: auto runs it on one thread (model/threads.py)
    assert compiled.get_property("INFERENCE_NUM_THREADS") == 1
    assert compiled.get_property("NUM_STREAMS") == 1


def test_wrong_image_size_is_explained(ov_fp32):
    with pytest.raises(
        ConfigError, match=r"compiled for images \[B,3,56,56\], got \[1, 3, 70, 70"
    ):
        ov_fp32.encode(torch.zeros(1, 3, 70, 70))


@pytest.mark.slow
def test_int8_is_close_and_says_so(torch_model, inputs):
    require("nncf")
    images, dense, desc = inputs
    model = OpenVINOModel(torch_model, "int8", calibration=synthetic_calibration(4, 56))
    assert model.fingerprint.startswith("random-init:0+ov-int8|tiny|")
    got_dense, got_desc = model.encode(images)
    cosine = (got_desc * desc).sum(-1)
    assert cosine.min() > 0.99, cosine
    scores = model.pair_scores(dense[0], dense[1:])
    with torch.inference_mode():
        want = torch_model.pair_scores(dense[0], dense[1:])
    # A 32-wide random network quantizes coarsely: errors ~0.1 of a ~1.0 spread of scores here
    # (a broken quantization, e.g. with SmoothQuant, was off by more than the spread). The
    # agreement that matters is measured on trained weights by benchmarks/bench_model.py.
    assert torch.isfinite(scores).all() and (scores - want).abs().max() < 0.15
    scorer = model.query_scorer(dense[0])  # the one-direction graphs, quantized alike
    both = scorer.logits(dense[1:], "query") + scorer.logits(dense[1:], "candidate")
    assert (both - want).abs().max() < 0.15


def test_calibration_scenes_are_fixed_and_varied():
    a, b = synthetic_scene(3), synthetic_scene(4)
    assert a.shape == (240, 320, 3) and a.dtype == np.uint8
    np.testing.assert_array_equal(a, synthetic_scene(3))
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 10
    batch = synthetic_calibration(2, 56)
    assert batch.shape == (2, 3, 56, 56) and batch.dtype == torch.float32
    with pytest.raises(ConfigError, match="int8 calibration needs at least 2 images"):
        OpenVINOModel(build_pairvpr(ModelConfig.tiny(), seed=0), "int8", calibration=batch[:1])
