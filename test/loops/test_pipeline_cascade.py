"""The re-rank cascade through the pipeline (tiny random network, 14 frames): `rerank_cascade`
false gives exactly the records the pipeline gave before the cascade existed; on, the same
decisions, every candidate's directions explicit, and the decoder passes counted."""

from __future__ import annotations

import numpy as np
import pytest

from pair_vpr_ros.loops import cascade
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline

ORDER = [0, 1, 2, 3, 4, 5, 0, 6, 2, 7, 1, 3, 5, 4]
CONFIG = dict(
    global_floor=-1.0, score_threshold=0.6, keyframe_max_similarity=0.99999,
    exclude_recent_s=2.5, exclude_recent_keyframes=1, top_k=4, map_growth="all",
    sequence_margin=0.5, temporal_tolerance=1,
)  # fmt: skip
# (query, match, pair score, rank before, rank after, candidates, scored, accepted, reason):
# the records of main before the cascade (2026-11-28, commit 2b1c4db) on this fixture
TODAY = [
    (3, 0, 0.13862, 1, 1, 1, 1, False, "score below threshold"),
    (4, 0, 0.44111, 2, 1, 2, 2, False, "score below threshold"),
    (5, 0, 1.2753, 1, 1, 3, 3, True, ""),
    (6, 1, 0.63658, 3, 1, 4, 4, True, ""),
    (7, 0, 1.0144, 2, 1, 4, 4, True, ""),
    (8, 2, 0.03308, 1, 1, 4, 4, False, "score below threshold"),
    (9, 6, 0.67157, 3, 1, 4, 4, True, ""),
    (10, 6, 0.60841, 3, 1, 4, 4, True, ""),
    (11, 1, -0.30072, 4, 1, 4, 4, False, "score below threshold"),
    (12, 7, 0.67217, 4, 1, 4, 4, True, ""),
    (13, 10, -0.60893, 3, 1, 4, 4, False, "score below threshold"),
]


def records(model, **config):
    rng = np.random.default_rng(5)
    places = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(8)]
    pipe = LoopClosurePipeline(model, DetectorConfig(**{**CONFIG, **config}))
    out = [pipe.process(Frame(float(t), places[p], "cam")) for t, p in enumerate(ORDER)]
    rows = [
        (r.query_id, r.match_id, r.pair_score, r.rank_before, r.rank_after, r.candidates,
         r.scored, r.accepted, r.reason)
        for r in (o.loop for o in out) if r is not None
    ]  # fmt: skip
    return rows, out, pipe


def same(rows, want, scored=True):
    assert len(rows) == len(want)
    for got, expected in zip(rows, want, strict=True):
        assert got[2] == pytest.approx(expected[2], abs=2e-5)
        keep = [0, 1, 3, 4, 5, 6, 7, 8] if scored else [0, 1, 3, 4, 5, 7, 8]
        assert [got[i] for i in keep] == [expected[i] for i in keep]


@pytest.mark.parametrize("explicit", [False, True])
def test_cascade_off_gives_the_records_of_before(tiny_model, explicit):
    config = {"rerank_cascade": False} if explicit else {}
    rows, out, pipe = records(tiny_model, **config)
    same(rows, TODAY)
    assert pipe.counts.decoder_passes == 2 * pipe.counts.candidates_scored == 2 * 38
    assert pipe.counts.rerank_skipped == 0
    assert all(c.directions == 2 for o in out for c in o.candidates)


def test_cascade_on_decides_the_same_from_fewer_passes(tiny_model, monkeypatch):
    monkeypatch.setattr(cascade, "MIN_PAIRS", 12)  # bounds after 3 keyframes, not 64 pairs
    rows, out, pipe = records(tiny_model, rerank_cascade=True)
    same(rows, TODAY, scored=False)
    assert [r[6] for r in rows][-6:] == [3, 4, 4, 2, 4, 3]  # rejected ones: left one way
    assert [c.directions for c in out[-1].candidates] == [2, 1, 2, 2]
    assert [c.directions for c in out[-3].candidates] == [2, 1, 1, 2]
    assert pipe.counts.decoder_passes == 72 < 2 * 38
    assert pipe.detector.cascade.stats.pairs == pipe.counts.candidates_scored == 34
