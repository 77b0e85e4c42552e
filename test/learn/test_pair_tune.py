"""Stage two on drives (`pair_tune`, `drive_pairs`): exact mining on hand-placed keyframes, only
the pair classifier trains, a resumed run ends where an uninterrupted one does."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from drive_maps import A, X, loop_drive, tiny_checkpoint, write_drive

from pair_vpr_ros.learn.train import pair_tune
from pair_vpr_ros.learn.train.drive_pairs import MiningRule, detection_ap, load_drive, mine_drive
from pair_vpr_ros.learn.train.losses import pair_bce
from pair_vpr_ros.model import load_pairvpr

RULE = MiningRule(top_k=2, exclude_recent_s=2.5, exclude_recent_keyframes=1)


def hand_arrays(pose_of_last: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    stamps = np.arange(len(X), dtype=np.float64)
    positions = np.array([[x, 0.0, 0.0] for x in X])
    if not pose_of_last:
        positions[-1] = np.nan  # keyframe 7 has no pose
    desc = np.array([[math.cos(a), math.sin(a)] for a in A])
    return stamps, positions, desc


def test_mining_follows_the_detector_exclusion_and_the_radii() -> None:
    queries = mine_drive(*hand_arrays(), RULE)
    # q0-q2: nothing eligible (q2's only older keyframe is 2 s old < 2.5 s); q7: no pose
    assert [q.query for q in queries] == [3, 4, 5, 6]
    got = {
        q.query: (q.candidates.tolist(), q.positives, q.negatives, q.has_match) for q in queries
    }
    assert got[3] == ([0], (0,), (), True)  # no negative: not trainable
    assert got[4] == ([1, 0], (0,), (1,), True)  # keyframe 3 is the newest: excluded
    assert got[5] == ([1, 0], (), (1, 0), False)  # no positive: not trainable
    # keyframe 3 (1 m away) is not in the top-2 but is the nearest eligible: a positive too
    assert got[6] == ([2, 0], (0, 3), (2,), True)
    assert [q.query for q in queries if q.trainable] == [4, 6]
    assert [q.query for q in queries if q.lonely] == [5]  # new ground with hard negatives
    np.testing.assert_allclose(queries[1].distance, [98.5, 1.5])
    np.testing.assert_allclose(queries[1].similarity, [math.cos(0.05), math.cos(0.3)])


def test_mining_leaves_candidates_between_the_radii_out() -> None:
    stamps, positions, desc = hand_arrays()
    positions[0] = [13.5, 0.0, 0.0]  # 12 m from keyframe 4, 11.5 m from keyframe 6
    queries = {q.query: q for q in mine_drive(stamps, positions, desc, RULE)}
    assert (queries[4].positives, queries[4].negatives) == ((), (1,))
    assert (queries[6].positives, queries[6].negatives) == ((3,), (2,))


def test_detection_ap_counts_queries_with_a_match() -> None:
    # ranked: hit, miss, hit; 4 queries have a true match -> (1 + 2/3) / 4
    ap = detection_ap(np.array([0.9, 0.5, 0.7]), np.array([True, True, False]), 4)
    assert ap == pytest.approx((1 + 2 / 3) / 4)
    assert detection_ap(np.array([1.0]), np.array([False]), 0) == 0.0


def test_load_drive_reads_the_map_as_stored(tmp_path: Path) -> None:
    _, model = tiny_checkpoint(tmp_path / "init.pt")
    path = write_drive(tmp_path / "map", model)
    shape = (model.num_patches, model.config.embed_dim)
    drive = load_drive(path, RULE, shape, model.weights_id)
    assert drive.dense.dtype == torch.float32 and drive.dense.shape == (len(X), *shape)
    expected = mine_drive(*hand_arrays(pose_of_last=True), RULE)
    assert [(q.query, q.positives, q.negatives) for q in drive.queries] == [
        (q.query, q.positives, q.negatives) for q in expected
    ]


def test_lonely_rows_come_from_new_ground_on_a_stream_of_their_own() -> None:
    queries = mine_drive(*hand_arrays(), RULE)
    pools, lonely = [[q for q in queries if q.trainable]], [[q for q in queries if q.lonely]]
    rows = pair_tune.sample_lonely(lonely, 6, seed=3, step=7)
    assert [d for d, _ in rows] == [0] and len(rows[0][1]) == 6
    assert set(rows[0][1]) <= {(5, 1), (5, 0)}  # query 5 against its own negatives
    assert rows == pair_tune.sample_lonely(lonely, 6, seed=3, step=7)
    assert pair_tune.sample_lonely(lonely, 0, 3, 7) == [] == pair_tune.sample_lonely([[]], 6, 3, 7)
    # the training rows of a step come from their own stream: (seed, step) alone fixes them
    batch = pair_tune.sample_batch(pools, 4, 3, 7)
    assert [d for d, _ in batch] == [0] and len(batch[0][1]) == 4
    assert set(batch[0][1]) <= {(4, 0, 1), (6, 0, 2), (6, 3, 2)}
    assert batch == pair_tune.sample_batch(pools, 4, 3, 7)


def test_lonely_rows_enter_the_loss_as_negatives_in_both_orders(tmp_path: Path) -> None:
    _, model = tiny_checkpoint(tmp_path / "init.pt")
    drive = load_drive(write_drive(tmp_path / "map", model), RULE,
                       (model.num_patches, model.config.embed_dim), model.weights_id)  # fmt: skip
    picked, lonely = [(0, [(4, 0, 1), (6, 3, 2)])], [(0, [(5, 1), (5, 0)])]
    got = pair_tune.batch_loss(model, [drive], picked, 1, lonely)
    d = drive.dense
    logit = lambda i, j: model.pair_logits(d[[i]], d[[j]])  # noqa: E731
    pos = [logit(4, 0), logit(6, 3), logit(0, 4), logit(3, 6), logit(4, 4)]
    neg = [logit(4, 1), logit(6, 2), logit(1, 4), logit(2, 6)]
    neg += [logit(5, 1), logit(5, 0), logit(1, 5), logit(0, 5)]
    want = pair_bce(torch.cat(pos), torch.cat(neg))
    assert got.item() == pytest.approx(want.item(), rel=1e-5)
    assert got.item() != pytest.approx(pair_tune.batch_loss(model, [drive], picked, 1).item())


def _run(tmp_path: Path, out: str, steps: int, *extra: str) -> Path:
    argv = ["--init", str(tmp_path / "init.pt"), "--drive", str(tmp_path / "d1")]
    argv += ["--drive", str(tmp_path / "d2"), "--out", str(tmp_path / out)]
    argv += ["--steps", str(steps), "--batch", "4", "--twins", "1", "--no-progress"]
    assert pair_tune.main([*argv, *extra]) == 0
    return tmp_path / out / pair_tune.FINAL


@pytest.fixture()
def drives(tmp_path: Path) -> Path:
    _, model = tiny_checkpoint(tmp_path / "init.pt")
    xs, angles = loop_drive()
    write_drive(tmp_path / "d1", model, xs, angles, seed=1)
    write_drive(tmp_path / "d2", model, xs, angles, seed=2)
    return tmp_path


def test_only_the_pair_classifier_trains(drives: Path) -> None:
    val = ["--val", str(drives / "d2"), "--eval-every", "2", "--log-every", "1"]
    final = _run(drives, "out", 2, *val)
    before = load_pairvpr(drives / "init.pt").state_dict()
    after = load_pairvpr(final).state_dict()
    assert before.keys() == after.keys()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    frozen = [k for k in before if not k.startswith(pair_tune.PAIR_CLASSIFIER)]
    assert frozen and not changed & set(frozen)  # encoder, globalizer: bit-identical
    assert any(k.startswith("dec_blocks") for k in changed)
    assert any(k.startswith("classvprmodule") for k in changed)
    stored = torch.load(final, weights_only=True)
    assert set(stored) == {"model", "arch", "format"}
    lines = (drives / "out" / "train_log.jsonl").read_text().splitlines()
    log = [json.loads(line) for line in lines]
    assert [r["step"] for r in log] == [0, 1, 2, 2]
    assert set(log[0]["val"]) == {
        "global", "pair", "rerank_10", "rerank_20", "rerank_40", "queries", "with_match",
    }  # fmt: skip
    assert log[0]["val"]["with_match"] > 0 and "loss" in log[1]


def test_resume_ends_where_an_uninterrupted_run_does(drives: Path) -> None:
    whole = load_pairvpr(_run(drives, "whole", 4, "--save-every", "2")).state_dict()
    _run(drives, "part", 2, "--save-every", "2")
    resumed_path = _run(drives, "resumed", 4, "--resume", str(drives / "part" / "last.pt"))
    resumed = load_pairvpr(resumed_path).state_dict()
    assert all(torch.equal(whole[k], resumed[k]) for k in whole)
    half = load_pairvpr(drives / "part" / pair_tune.FINAL).state_dict()
    assert not all(torch.equal(whole[k], half[k]) for k in whole)  # steps 3-4 did train


def _export_main():  # noqa: ANN202
    script = Path(__file__).resolve().parents[2] / "scripts" / "export_demo_model.py"
    spec = importlib.util.spec_from_file_location("export_demo_model", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main


def test_export_takes_the_pair_tune_output_when_present(drives: Path) -> None:
    train = drives / "train"
    (train / "stage2").mkdir(parents=True)
    shutil.copy(drives / "init.pt", train / "stage2" / "stage2_final.pt")
    export = _export_main()
    assert export([str(train), str(drives / "a.pth")]) == 0
    summary = json.loads((drives / "a.json").read_text())
    assert summary["weights_from"] == "stage2/stage2_final.pt" and "pair_tune" not in summary
    _run(drives, "train/pair_tune", 2, "--val", str(drives / "d2"), "--eval-every", "1")
    assert export([str(train), str(drives / "b.pth")]) == 0
    summary = json.loads((drives / "b.json").read_text())
    assert summary["weights_from"] == "pair_tune/pair_tune_final.pt"
    assert summary["pair_tune_config"]["steps"] == 2 and summary["pair_tune_config"]["twins"] == 1
    assert [summary["pair_tune_val"][k]["step"] for k in ("first", "last")] == [0, 2]
    tuned = load_pairvpr(drives / "train" / "pair_tune" / pair_tune.FINAL).state_dict()
    shipped = load_pairvpr(drives / "b.pth").state_dict()
    assert all(torch.equal(tuned[k].half().float(), shipped[k]) for k in tuned)
