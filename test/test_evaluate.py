"""Recall@N metric, re-ranking order, end-to-end evaluation and the pairvpr-eval CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic_data import make_utm_eval_set

from pair_vpr_ros.datasets import load_eval_set, read_rgb
from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.evaluate import (
    EvalConfig,
    EvalResult,
    _rerank,
    evaluate_set,
    format_table,
    main,
    recall_at_n,
)
from pair_vpr_ros.model import ModelConfig, build_pairvpr, preprocess


def test_recall_at_n_hand_made_case() -> None:
    ranked = [[3, 1, 2], [0, 5, 6], [7, 8, 9], [4, 4, 2]]
    positives = [np.array([1]), np.array([0, 6]), np.array([], dtype=np.int64), np.array([2])]
    assert recall_at_n(ranked, positives, [1, 2, 3, 10]) == {1: 0.25, 2: 0.5, 3: 0.75, 10: 0.75}
    with pytest.raises(ConfigError, match=r"3 result lists for 4 queries"):
        recall_at_n(ranked[:3], positives, [1])


class _StubModel:
    def pair_scores(self, query: torch.Tensor, cands: torch.Tensor) -> torch.Tensor:
        return cands[:, 0, 0].float()  # the stub "score" is stored in the first token


class _StubMap:
    def get_dense(self, ids: list[int]) -> np.ndarray:
        scores = {5: 0.1, 3: 0.9, 9: 0.5, 1: 2.0}
        return np.array([[[scores[i]]] for i in ids], dtype=np.float16)


def test_rerank_sorts_top_k_by_pair_score_and_keeps_the_tail() -> None:
    query = torch.zeros(1, 1)
    assert _rerank(_StubModel(), query, _StubMap(), [5, 3, 9, 1], k=3) == [3, 9, 5, 1]
    assert _rerank(_StubModel(), query, _StubMap(), [5, 3, 9, 1], k=10) == [1, 3, 9, 5]


@pytest.fixture(scope="module")
def tiny_model() -> torch.nn.Module:
    torch.manual_seed(0)
    return build_pairvpr(ModelConfig.tiny(), seed=0)


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
        cands = db_dense[row].half().float()  # the map stores float16 tokens
        with torch.inference_mode():
            scores = model.pair_scores(q_dense[q], cands)
        reranked.append([row[i] for i in torch.argsort(scores, descending=True).tolist()])
    return order, reranked


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
    assert main([str(tmp_path / "nope"), "--random-init", "tiny"]) == 2
    assert "error: dataset folder " in capsys.readouterr().err
    root = make_utm_eval_set(tmp_path / "set", places=2)
    assert main([str(root)]) == 2
    assert capsys.readouterr().err.startswith("error: give a checkpoint (--weights PATH)")
    assert main([str(root), "--checkpoint", str(tmp_path / "missing.pth")]) == 2
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
