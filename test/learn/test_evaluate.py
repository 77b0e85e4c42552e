"""Recall@N metric, re-ranking order, end-to-end evaluation and the pairvpr-eval CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic_data import make_utm_eval_set

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.learn import recall
from pair_vpr_ros.learn.eval_sets import load_eval_set
from pair_vpr_ros.learn.evaluate import format_table, main
from pair_vpr_ros.learn.image_files import read_rgb
from pair_vpr_ros.learn.recall import (
    EvalConfig,
    EvalResult,
    StageSeconds,
    evaluate_set,
    fill_map,
    rank_queries,
    recall_at_n,
    rerank,
)
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.model import preprocess
from pair_vpr_ros.place_map import PlaceMap


def test_recall_at_n_hand_made_case() -> None:
    ranked = [[3, 1, 2], [0, 5, 6], [7, 8, 9], [4, 4, 2]]
    positives = [np.array([1]), np.array([0, 6]), np.array([], dtype=np.int64), np.array([2])]
    assert recall_at_n(ranked, positives, [1, 2, 3, 10]) == {1: 0.25, 2: 0.5, 3: 0.75, 10: 0.75}
    with pytest.raises(ConfigError, match=r"3 result lists for 4 queries"):
        recall_at_n(ranked[:3], positives, [1])


def test_rerank_orders_the_first_k_hits_by_pair_score_and_keeps_the_tail(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    scores = {5: 0.1, 3: 0.9, 9: 0.5, 1: 2.0}
    monkeypatch.setattr(
        recall, "map_pair_scores", lambda model, pmap, q, ids: np.array([scores[i] for i in ids])
    )
    hits = [(5, 0.9), (3, 0.8), (9, 0.7), (1, 0.6)]
    top3 = rerank(None, None, np.zeros((1, 1)), hits, k=3)
    assert [(c.id, c.rank_before) for c in top3] == [(3, 2), (9, 3), (5, 1), (1, 4)]
    assert [c.pair_score for c in top3[:3]] == [0.9, 0.5, 0.1] and math.isnan(top3[3].pair_score)
    assert [c.id for c in rerank(None, None, np.zeros((1, 1)), hits, k=10)] == [1, 3, 9, 5]
    assert rerank(None, None, np.zeros((1, 1)), [], k=10) == []
    # with the similarity weighted in (x2): 0.1+1.8, 0.9+1.6, 0.5+1.4 -> 3, 5, 9
    weighted = rerank(None, None, np.zeros((1, 1)), hits, k=3, global_weight=2.0)
    assert [c.id for c in weighted] == [3, 5, 9, 1]


def _brute_force_rankings(model, data) -> tuple[list, list]:  # noqa: ANN001
    def encode(paths):  # noqa: ANN001, ANN202
        images = torch.stack([preprocess(read_rgb(p), 56) for p in paths])
        with torch.inference_mode():
            return model.encode(images)

    db_dense, db_desc = encode(data.database)
    q_dense, q_desc = encode(data.queries)
    order = torch.argsort(q_desc @ db_desc.T, dim=1, descending=True).tolist()
    reranked = []
    for q, row in enumerate(order):
        cands = db_dense[row].half().float()  # the map stores float16 tokens ...
        with torch.inference_mode():  # ... and the node rounds its query the same way
            scores = model.pair_scores(q_dense[q].half().float(), cands)
        reranked.append([row[i] for i in torch.argsort(scores, descending=True).tolist()])
    return order, reranked


@pytest.mark.slow
def test_evaluate_set_matches_brute_force(tmp_path: Path, tiny_model) -> None:  # noqa: ANN001
    data = load_eval_set(make_utm_eval_set(tmp_path / "set", places=5))
    cfg = EvalConfig(
        datasets=[],
        recall_ns=(1, 2, 5),
        rerank_k=5,
        batch_size=2,
        workers=0,
        progress=False,
        work_dir=tmp_path,
    )
    result = evaluate_set(tiny_model, data, cfg)
    order, reranked = _brute_force_rankings(tiny_model, data)
    assert result.recall_global == recall_at_n(order, data.positives, (1, 2, 5))
    assert result.recall_rerank == recall_at_n(reranked, data.positives, (1, 2, 5))
    assert result.recall_global[5] == 1.0 and result.num_queries == 5
    assert result.bytes_per_image == 512 * 4 + 16 * 32 * 2
    global_only = evaluate_set(
        tiny_model, data, EvalConfig(datasets=[], rerank_k=0, workers=0, progress=False)
    )
    assert global_only.recall_rerank == {} and global_only.rerank_ms_per_query == 0.0


@pytest.mark.slow
def test_evaluation_ranks_as_the_node_pipeline(tmp_path: Path, tiny_model) -> None:  # noqa: ANN001
    """Same map, same query image: evaluate's re-ranked candidates are the pipeline's candidates
    in pair-score order (ids and scores equal to the bit), and its best is the loop record's."""
    data = load_eval_set(make_utm_eval_set(tmp_path / "set", places=6))
    cfg = EvalConfig(
        datasets=[], recall_ns=(1, 6), rerank_k=4, batch_size=1, workers=0, progress=False
    )
    detector = DetectorConfig(
        top_k=4,
        exclude_recent_s=0.0,
        exclude_recent_keyframes=0,
        keyframe_max_similarity=1.0,  # random-init descriptors are all alike
        mode="localization",
    )
    shape = (tiny_model.num_patches, tiny_model.config.embed_dim)
    reordered = 0
    with PlaceMap(tiny_model.config.desc_dim, shape, tiny_model.fingerprint) as pmap:
        spent = StageSeconds()
        fill_map(tiny_model, data, cfg, pmap, spent)
        evaluated = list(rank_queries(tiny_model, data, cfg, pmap, spent))
        pipeline = LoopClosurePipeline(tiny_model, detector, place_map=pmap)
        for q, (global_ids, reranked) in enumerate(evaluated):
            outcome = pipeline.process(Frame(stamp=100.0 + q, rgb=read_rgb(data.queries[q])))
            assert outcome.skipped == "" and outcome.keyframe_id is None
            node = sorted(outcome.candidates, key=lambda c: (-c.pair_score, c.rank_before))
            assert [c.id for c in outcome.candidates] == global_ids[:4]
            assert [(c.id, c.pair_score) for c in reranked[:4]] == [
                (c.id, c.pair_score) for c in node
            ]
            assert outcome.loop.match_id == reranked[0].id
            assert [c.id for c in reranked[4:]] == global_ids[4:]  # the tail keeps global order
            reordered += [c.id for c in reranked] != global_ids
    assert reordered > 0  # the pair scores did change some order


def test_cli_writes_table_and_json(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root = make_utm_eval_set(tmp_path / "set", places=4)
    out = tmp_path / "res" / "eval.json"
    argv = [
        str(root),
        "--random-init",
        "tiny",
        "--rerank-k",
        "2",
        "--recall",
        "1",
        "3",
        "--json",
        str(out),
        "--quiet",
        "--workers",
        "0",
        "--device",
        "cpu",
        "--index",
        "ivf",  # exact below 25,000 images, as flat
    ]
    assert main(argv) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split()[:5] == ["dataset", "db", "queries", "R@1", "R@3"]
    assert table[1].split()[:3] == ["set", "4", "4"]
    payload = json.loads(out.read_text())
    assert payload["checkpoint"] == "random:tiny"
    assert payload["results"][0]["rerank_k"] == 2
    assert set(payload["results"][0]["recall_global"]) == {"1", "3"}


def test_cli_errors(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main([str(tmp_path / "nope"), "--random-init", "tiny"]) == 1  # bad data
    assert "error: dataset folder " in capsys.readouterr().err
    root = make_utm_eval_set(tmp_path / "set", places=2)
    assert main([str(root)]) == 1  # no weights anywhere (test/conftest.py), one line
    err = capsys.readouterr().err
    assert err.startswith(
        "error: no Pair-VPR weights found; looked in --weights: not given; $PAIRVPR_WEIGHTS: "
        "not set; "
    )
    assert err.count("\n") == 1
    assert main([str(root), "--checkpoint", str(tmp_path / "missing.pth")]) == 1
    assert "missing.pth does not exist" in capsys.readouterr().err


def test_format_table_values() -> None:
    r = EvalResult(
        "pitts", 10, 4, 0, {1: 0.5, 5: 1.0}, {1: 0.75, 5: 1.0}, 100, 12.34, 0.05, 31.0, 2048
    )
    lines = format_table([r]).splitlines()
    assert lines[1].split() == [
        "pitts",
        "10",
        "4",
        "50.0",
        "100.0",
        "75.0",
        "100.0",
        "12.3",
        "0.05",
        "31.0",
        "2.0",
    ]


def test_weights_are_found_as_the_node_and_the_replay_find_them(tmp_path, capsys, monkeypatch):
    root = make_utm_eval_set(tmp_path / "set", places=2)
    monkeypatch.setenv("PAIRVPR_WEIGHTS", "random-tiny")  # as a robot's environment sets it
    out = tmp_path / "eval.json"
    assert main([str(root), "--rerank-k", "1", "--recall", "1", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["checkpoint"] == "random:tiny"
    capsys.readouterr()
    monkeypatch.setenv("PAIRVPR_WEIGHTS", str(tmp_path / "missing.pth"))
    assert main([str(root)]) == 1
    err = capsys.readouterr().err
    assert "missing.pth does not exist" in err and "(weights from $PAIRVPR_WEIGHTS)" in err
