"""The shared pipeline with a tiny random network. Random-init descriptors are nearly collinear,
so these tests let only identical images through the global floor: revisits are exact repeats."""

from __future__ import annotations

import numpy as np
import pytest
from exact_match import EXACT_MATCH

from pair_vpr_ros.detector import DetectorConfig
from pair_vpr_ros.errors import ConfigError, MapFingerprintError
from pair_vpr_ros.model import ModelConfig, build_pairvpr
from pair_vpr_ros.pipeline import Frame, LoopClosurePipeline

EXACT = EXACT_MATCH  # only exact repeats of images are loops (see exact_match.py)


@pytest.fixture(scope="module")
def model():
    return build_pairvpr(ModelConfig.tiny(), seed=0)


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


def test_revisits_found_and_recent_frames_excluded(model, places):
    pipe = LoopClosurePipeline(model, DetectorConfig(**EXACT))
    # place 5 repeats at t=5,6 (recent: excluded); places 0 and 2 are revisited later.
    out = run(pipe, places, [0, 1, 2, 3, 4, 5, 5, 0, 2])
    assert [o.keyframe_id for o in out] == [0, 1, 2, 3, 4, 5, None, 6, 7]
    assert out[6].skipped == "similar to previous keyframe"
    assert loops(out) == [(6, 0), (7, 2)]
    rec = out[8].loop
    assert (rec.query_stamp, rec.match_stamp, rec.rank_before, rec.rank_after) == (8.0, 2.0, 1, 1)
    assert pipe.place_map.meta(6).pose == (7.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    assert pipe.counts["loops"] == 2 and pipe.counts["keyframes"] == 8


def test_batching_gives_the_same_records(model, places):
    order = [0, 1, 2, 3, 0, 1, 4, 2]
    a = run(LoopClosurePipeline(model, DetectorConfig(**EXACT)), places, order, batch_size=1)
    b = run(LoopClosurePipeline(model, DetectorConfig(**EXACT)), places, order, batch_size=4)
    assert loops(a) == loops(b) == [(4, 0), (5, 1), (7, 2)]
    for x, y in zip(a, b, strict=True):  # batched GEMMs round differently: equal to ~1e-6
        assert (x.keyframe_id, x.skipped) == (y.keyframe_id, y.skipped)
        if x.loop:
            assert x.loop.pair_score == pytest.approx(y.loop.pair_score, abs=1e-5, nan_ok=True)
            assert x.loop.global_similarity == pytest.approx(y.loop.global_similarity, abs=1e-5)


def test_rate_limit_skips_without_encoding(model, places):
    pipe = LoopClosurePipeline(model, DetectorConfig(**EXACT, min_frame_interval=1.0))
    out = run(pipe, places, [0, 1, 2, 3], dt=0.5)
    assert [o.skipped for o in out] == ["", "rate limited", "", "rate limited"]
    assert pipe.counts["encoded"] == 2


def test_localization_never_grows_the_map(model, places):
    pipe = LoopClosurePipeline(model, DetectorConfig(**EXACT))
    run(pipe, places, [0, 1, 2, 3])
    pipe.set_mode("localization")
    out = run(pipe, places, [4, 0, 1], t0=10.0)
    assert len(pipe.place_map) == 4
    assert all(o.keyframe_id is None for o in out)
    assert [(o.loop.query_id, o.loop.match_id) for o in out if o.loop and o.loop.accepted] == [
        (-1, 0),
        (-1, 1),
    ]


def test_save_load_gives_identical_results(model, places, tmp_path):
    pipe = LoopClosurePipeline(model, DetectorConfig(**EXACT))
    run(pipe, places, [0, 1, 2, 3])
    pipe.save_map(tmp_path / "map")
    again = run(pipe, places, [5, 2], t0=10.0)
    pipe.close()  # a map saved to a folder keeps it locked against other writers
    fresh = LoopClosurePipeline(model, DetectorConfig(**EXACT))
    assert fresh.load_map(tmp_path / "map") == 4
    query = run(fresh, places, [5, 2], t0=10.0)
    assert [o.loop and o.loop.to_dict() for o in query] == [
        o.loop and o.loop.to_dict() for o in again
    ]
    assert loops(query) == [(5, 2)]


def test_map_of_another_model_is_refused(model, places, tmp_path):
    pipe = LoopClosurePipeline(model, DetectorConfig(**EXACT))
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


def test_bad_batch_size(model):
    with pytest.raises(ConfigError, match="batch size must be >= 1, got 0"):
        list(LoopClosurePipeline(model).process_many([], batch_size=0))


def test_geometric_verification_in_the_pipeline(model):
    rng = np.random.default_rng(5)
    scenes = []
    for _ in range(4):
        img = np.full((120, 160, 3), 80, np.uint8)
        for _ in range(60):
            x, y = (int(v) for v in rng.integers(0, 150, 2))
            img[y % 110 : y % 110 + 10, x : x + 10] = rng.integers(0, 256, 3)
        scenes.append(img)
    pipe = LoopClosurePipeline(
        model, DetectorConfig(**EXACT, geometric_verification=True, min_inliers=15)
    )
    out = run(pipe, scenes, [0, 1, 2, 3, 0])
    rec = out[4].loop
    assert rec.accepted and rec.inliers >= 15 and rec.inlier_ratio > 0.5


def test_map_can_be_used_from_another_thread(model, places, tmp_path):
    import threading

    pipe = LoopClosurePipeline(model, DetectorConfig(**EXACT))
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
