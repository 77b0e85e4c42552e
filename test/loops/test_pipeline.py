"""The shared pipeline with a tiny random network. Random-init descriptors are nearly collinear,
so these tests let only identical images through the global floor: revisits are exact repeats."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from exact_match import EXACT_MATCH

from pair_vpr_ros.errors import ConfigError, MapFingerprintError
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame, PipelineCounts
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.messages.loop import loop_messages
from pair_vpr_ros.model import ModelConfig, PairVPRModel, build_pairvpr

EXACT = EXACT_MATCH  # only exact repeats of images are loops (see exact_match.py)


@pytest.fixture(scope="module")
def places():
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(6)]


def run(pipe, places, order, batch_size=1, dt=1.0, t0=0.0):
    frames = [
        Frame(stamp=t0 + t * dt, rgb=places[p], frame_id="cam", pose=(t, 0, 0, 0, 0, 0, 1))
        for t, p in enumerate(order)
    ]
    return list(pipe.process_many(frames, batch_size=batch_size))


def loops(outcomes):
    return [(o.loop.query_id, o.loop.match_id) for o in outcomes if o.loop and o.loop.accepted]


def test_revisits_found_and_recent_frames_excluded(tiny_model, places):
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT))
    # place 5 repeats at t=5,6 (recent: excluded); places 0 and 2 are revisited later.
    out = run(pipe, places, [0, 1, 2, 3, 4, 5, 5, 0, 2])
    assert [o.keyframe_id for o in out] == [0, 1, 2, 3, 4, 5, None, 6, 7]
    assert out[6].skipped == "similar to previous keyframe"
    assert loops(out) == [(6, 0), (7, 2)]
    rec = out[8].loop
    assert (rec.query_stamp, rec.match_stamp, rec.rank_before, rec.rank_after) == (8.0, 2.0, 1, 1)
    assert pipe.place_map.meta(6).pose == (7.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    rejected = [o.loop.query_id for o in out if o.loop and not o.loop.accepted]
    assert rejected == [3, 4, 5]  # their best candidate is below the global floor
    assert pipe.counts == PipelineCounts(
        encoded=9,
        similar_to_keyframe=1,
        keyframes=8,
        loops=2,
        rejected=3,
        pose_none=2,
        candidates_scored=2,
        decoder_passes=4,
        rerank_covered=2,
        rerank_skipped=3,
    )  # no intrinsics given: the two loops get no relative pose; the 3 rejected are not scored


def test_batching_gives_the_same_records(tiny_model, places):
    order = [0, 1, 2, 3, 0, 1, 4, 2]
    a = run(LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT)), places, order, batch_size=1)
    b = run(LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT)), places, order, batch_size=4)
    assert loops(a) == loops(b) == [(4, 0), (5, 1), (7, 2)]
    for x, y in zip(a, b, strict=True):  # batched GEMMs round differently: equal to ~1e-6
        assert (x.keyframe_id, x.skipped) == (y.keyframe_id, y.skipped)
        if x.loop:
            assert x.loop.pair_score == pytest.approx(y.loop.pair_score, abs=1e-5, nan_ok=True)
            assert x.loop.global_similarity == pytest.approx(y.loop.global_similarity, abs=1e-5)


@pytest.mark.slow
def test_outcomes_stay_in_frame_order_with_rate_limiting_for_every_batch_size(tiny_model, places):
    # Issue 13 #1: rate-limited frames used to overtake frames waiting in the batch.
    order = [0, 1, 1, 2, 3, 3, 0, 4, 1, 5, 2, 2, 0, 3, 4, 1, 5, 0]
    dts = [0.3, 0.6, 0.2, 0.7, 0.25, 0.9, 0.3, 0.6, 0.2, 0.8, 0.4, 0.5, 0.3, 0.6, 0.2, 0.7, 0.3]
    stamps = np.concatenate([[0.0], np.cumsum(dts)])
    frames = [Frame(float(t), places[p], "cam") for t, p in zip(stamps, order, strict=True)]
    config = DetectorConfig(**{**EXACT, "exclude_recent_s": 1.0}, min_frame_interval=0.5)

    def records(batch_size):
        pipe = LoopClosurePipeline(tiny_model, config)
        out = list(pipe.process_many(frames, batch_size=batch_size))
        assert [o.stamp for o in out] == [f.stamp for f in frames]
        return [
            (o.keyframe_id, o.skipped, o.loop and (o.loop.query_id, o.loop.match_id)) for o in out
        ], out

    reference, ref_out = records(1)
    assert sum(r[1] == "rate limited" for r in reference) == 9
    assert any(r[2] for r in reference)  # some frames were queried
    for batch_size in range(2, 17):
        got, out = records(batch_size)
        assert got == reference, batch_size
        for a, b in zip(ref_out, out, strict=True):
            if a.loop is not None:
                assert a.loop.pair_score == pytest.approx(b.loop.pair_score, abs=1e-5, nan_ok=True)


def test_rate_limit_skips_without_encoding(tiny_model, places):
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT, min_frame_interval=1.0))
    out = run(pipe, places, [0, 1, 2, 3], dt=0.5)
    assert [o.skipped for o in out] == ["", "rate limited", "", "rate limited"]
    assert (pipe.counts.encoded, pipe.counts.rate_limited) == (2, 2)


def test_localization_never_grows_the_map(tiny_model, places):
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT))
    run(pipe, places, [0, 1, 2, 3])
    pipe.set_mode("localization")
    out = run(pipe, places, [4, 0, 1], t0=10.0)
    assert len(pipe.place_map) == 4
    assert all(o.keyframe_id is None for o in out)
    assert [(o.loop.query_id, o.loop.match_id) for o in out if o.loop and o.loop.accepted] == [
        (-1, 0),
        (-1, 1),
    ]


def test_save_load_gives_identical_results(tiny_model, places, tmp_path):
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT))
    run(pipe, places, [0, 1, 2, 3])
    pipe.save_map(tmp_path / "map")
    again = run(pipe, places, [5, 2], t0=10.0)
    pipe.close()  # a map saved to a folder keeps it locked against other writers
    fresh = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT))
    assert fresh.load_map(tmp_path / "map") == 4
    query = run(fresh, places, [5, 2], t0=10.0)
    assert [o.loop and o.loop.to_dict() for o in query] == [
        o.loop and o.loop.to_dict() for o in again
    ]
    assert loops(query) == [(5, 2)]


def test_map_of_another_model_is_refused(tiny_model, places, tmp_path):
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT))
    run(pipe, places, [0])
    pipe.save_map(tmp_path / "map")
    assert pipe.load_map(tmp_path / "map") == 1  # reloading its own folder works
    pipe.clear_map()
    assert len(pipe.place_map) == 0 and loops(run(pipe, places, [0, 0])) == []
    pipe.close()
    other = LoopClosurePipeline(build_pairvpr(ModelConfig.tiny(), seed=1))
    with pytest.raises(
        MapFingerprintError, match="load it with the same weights and image size it was built with"
    ):
        other.load_map(tmp_path / "map")
    assert len(other.place_map) == 0


def test_bad_batch_size(tiny_model):
    with pytest.raises(ConfigError, match="batch size must be >= 1, got 0"):
        list(LoopClosurePipeline(tiny_model).process_many([], batch_size=0))


def test_geometric_verification_in_the_pipeline(tiny_model):
    rng = np.random.default_rng(5)
    scenes = []
    for _ in range(4):
        img = np.full((120, 160, 3), 80, np.uint8)
        for _ in range(60):
            x, y = (int(v) for v in rng.integers(0, 150, 2))
            img[y % 110 : y % 110 + 10, x : x + 10] = rng.integers(0, 256, 3)
        scenes.append(img)
    pipe = LoopClosurePipeline(
        tiny_model, DetectorConfig(**EXACT, geometric_verification=True, min_inliers=15)
    )
    out = run(pipe, scenes, [0, 1, 2, 3, 0])
    rec = out[4].loop
    assert rec.accepted and rec.inliers >= 15 and rec.inlier_ratio > 0.5


def test_map_can_be_used_from_another_thread(tiny_model, places, tmp_path):
    import threading

    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT))
    run(pipe, places, [0, 1])
    errors = []

    def worker():
        try:
            run(pipe, places, [2, 0], t0=10.0)
            pipe.save_map(tmp_path / "map")
        except Exception as err:  # surfaced below
            errors.append(err)

    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert errors == [] and len(pipe.place_map) == 4


class InterfaceOnly:
    """A back end that is no `PairVPR` and no `nn.Module`: it has exactly the members of
    `PairVPRModel`, as an OpenVINO or ONNX back end would."""

    def __init__(self, net) -> None:
        self._net = net
        self.config = net.config
        self.fingerprint = net.fingerprint
        self.num_patches = net.num_patches
        self.device = net.device
        self.dense_dtype = net.dense_dtype

    def encode(self, images):
        return self._net.encode(images)

    def pair_scores(self, query, cands, chunk=None):
        return self._net.pair_scores(query, cands, chunk)


def test_pipeline_needs_only_the_model_interface(tiny_model, places):
    narrow = InterfaceOnly(tiny_model)
    assert isinstance(narrow, PairVPRModel) and isinstance(tiny_model, PairVPRModel)
    assert not isinstance(narrow, torch.nn.Module)
    order = [0, 1, 2, 3, 0, 1]
    a = run(LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT)), places, order)
    b = run(LoopClosurePipeline(narrow, DetectorConfig(**EXACT)), places, order)
    assert [o.loop and o.loop.to_dict() for o in a] == [o.loop and o.loop.to_dict() for o in b]
    assert loops(b) == [(4, 0), (5, 1)]


@pytest.mark.parametrize("batch_size", [1, 4])
def test_stamps_going_back_start_a_session_and_never_pair_a_frame_with_itself(
    tiny_model, places, batch_size
):
    # Issue 17 #1: the same sequence played twice (`ros2 bag play --loop`). The second pass
    # used to match the first pass's keyframe at the very same stamp: pair [t, t].
    pipe = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT))
    order = [0, 1, 2, 3, 4, 5]
    first = run(pipe, places, order, batch_size=batch_size)
    second = run(pipe, places, order, batch_size=batch_size)
    assert [o.clock_jump_s for o in first + second] == [0.0] * 6 + [5.0] + [0.0] * 5
    assert pipe.counts.clock_jumps == 1
    assert loops(first) == [] and [o.keyframe_id for o in second] == [6, 7, 8, 9, 10, 11]
    for o in second:  # the first pass within exclude_recent_s (2.5 s) is excluded by stamp
        assert all(abs(c.stamp - o.stamp) >= EXACT["exclude_recent_s"] for c in o.candidates)
    assert loops(second) == []  # exact repeats only: each is at its own (excluded) stamp
    third = run(pipe, places, [3, 4, 5], batch_size=batch_size, t0=100.0)  # time moves on
    assert loops(third) == [(12, 3), (13, 4), (14, 5)]  # FAISS keeps the lower id on a tie
    earlier = run(pipe, places, [0, 1], batch_size=batch_size, t0=-50.0)  # another clock
    assert pipe.counts.clock_jumps == 2 and loops(earlier) == [(15, 0), (16, 1)]
    for o in earlier:  # loops into the "future": no LIO-SAM pair for them
        assert o.loop.match_stamp > o.loop.query_stamp and loop_messages(o.loop).pair is None


def test_a_p4_map_is_fitted_for_the_decoders_first_layer(tiny_model, places, tmp_path):
    """The pipeline hands the model's decoder_embed weight W to a new map and to a loaded one:
    dense codec p4 fits its basis on W x (a basis on the channels differs)."""
    from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta
    from pair_vpr_ros.place_map.dense_codec import BASIS_FROM, Basis, entry_bytes

    weight = tiny_model.decoder_embed.weight.detach().float().numpy()
    pipe = LoopClosurePipeline(
        tiny_model, DetectorConfig(**EXACT), index=IndexConfig(dense_codec="p4")
    )
    assert pipe._place_map._dense_weight is not None
    np.testing.assert_array_equal(pipe._place_map._dense_weight, weight)
    pipe.save_map(tmp_path / "map")
    pipe.close()
    fresh = LoopClosurePipeline(tiny_model, DetectorConfig(**EXACT))
    fresh.load_map(tmp_path / "map")
    np.testing.assert_array_equal(fresh._place_map._dense_weight, weight)
    m, rng = fresh._place_map, np.random.default_rng(1)
    for i in range(BASIS_FROM + 1):
        m.add(rng.normal(size=m.desc_dim), rng.normal(size=m.dense_shape), KeyframeMeta(stamp=i))
    tokens = m.get_dense(range(BASIS_FROM)).reshape(-1, m.dense_shape[1])  # what it was fit on
    size, n = entry_bytes(m.dense_shape, "p4"), m.dense_shape[0]
    for w, same in ((weight, True), (None, False)):
        fitted = Basis.fit(tokens, n, size, BASIS_FROM, w)
        assert np.array_equal(fitted.enc16, m.dense_basis.enc16) == same
    fresh.close()
