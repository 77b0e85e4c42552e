"""Bad-input matrix, stage two on drives (`pair_tune`): its flags, drive and validation maps,
checkpoints and output folder. Each is one `error: ...` line and a non-zero exit before any step,
with nothing written (a run already in --out is left as it was)."""

from __future__ import annotations

from pathlib import Path

import pytest
from drive_maps import loop_drive, tiny_checkpoint, write_drive

from pair_vpr_ros.learn.train import pair_tune

FLAGS = {
    "top-k zero": (["--top-k", "0"], 1, "error: top_k=0: must be >= 1"),
    "radii crossed": (["--negative-radius", "5"], 1, "negative_radius=5.0: must be >= gt_radius"),
    "gt-radius nan": (["--gt-radius", "nan"], 1, "error: gt_radius=nan: must be > 0 (metres)"),
    "lr zero": (["--lr", "0"], 1, "error: lr=0.0: must be > 0"),
    "batch zero": (["--batch", "0"], 1, "error: batch=0: must be >= 1"),
    "twins negative": (["--twins=-1"], 1, "error: twins=-1: must be >= 0"),
    "lonely negative": (["--lonely=-2"], 1, "error: lonely=-2: must be >= 0"),
    "lonely text": (["--lonely", "some"], 2, "argument --lonely: invalid int value: 'some'"),
    "steps zero": (["--steps", "0"], 1, "error: steps=0: must be >= 1"),
    "save-every zero": (["--save-every", "0"], 1, "error: save_every=0: must be >= 1"),
    "eval-every negative": (["--eval-every=-1"], 1, "eval_every=-1: must be >= 0 (0 = never)"),
    "top-k text": (["--top-k", "ten"], 2, "argument --top-k: invalid int value: 'ten'"),
    "device unknown": (["--device", "tpu"], 1, "error: device 'tpu' is not a torch device"),
}


@pytest.fixture()
def good(tmp_path: Path) -> list[str]:
    init, model = tiny_checkpoint(tmp_path / "init.pt")
    xs, angles = loop_drive()
    write_drive(tmp_path / "drive", model, xs, angles)
    write_drive(tmp_path / "no-poses", model, xs, angles, poses=False)
    write_drive(tmp_path / "other", model, xs, angles, fingerprint="sha256:0123|tiny")
    write_drive(tmp_path / "tokens", model, xs, angles, shape=(3, 4))
    write_drive(tmp_path / "straight", model, [30.0 * i for i in range(36)], angles)
    return ["--init", str(init), "--drive", str(tmp_path / "drive"), "--no-progress"]


def _fails(argv: list[str], code: int, message: str, capsys: pytest.CaptureFixture) -> None:
    assert pair_tune.main(argv) == code
    err = capsys.readouterr().err
    assert message in err, err


@pytest.mark.parametrize("case", list(FLAGS))
def test_bad_flag(tmp_path: Path, good: list[str], capsys: pytest.CaptureFixture, case: str):
    args, code, message = FLAGS[case]
    _fails([*good, "--out", str(tmp_path / "out"), *args], code, message, capsys)
    assert not (tmp_path / "out").exists()


INPUTS = {
    "drive without poses": (
        ["--drive", "{tmp}/no-poses"],
        "error: drive map {tmp}/no-poses has no keyframe poses: replay the bag with "
        "--pose-topic /ground_truth",
    ),
    "drive of other weights": (
        ["--drive", "{tmp}/other"],
        "error: drive map {tmp}/other was built with other weights (fingerprint "
        "'sha256:0123|tiny', --init is",
    ),
    "drive of other token shape": (
        ["--drive", "{tmp}/tokens"],
        "error: drive map {tmp}/tokens holds dense tokens (3, 4), the model makes",
    ),
    "nothing to mine": (
        ["--drive", "{tmp}/straight"],
        "error: drive map {tmp}/straight: no keyframe has both a positive (<= 10.0 m) and a "
        "hard negative (> 15.0 m) among its 10 global candidates",
    ),
    "val without a match": (
        ["--val", "{tmp}/straight"],
        "error: validation map {tmp}/straight: no keyframe has a true match (<= 10.0 m)",
    ),
    "drive missing": (
        ["--drive", "{tmp}/nowhere"],
        "error: {tmp}/nowhere/manifest.json is missing: {tmp}/nowhere is not a saved place map",
    ),
    "init missing": (
        ["--init", "{tmp}/none.pt"],
        "error: checkpoint {tmp}/none.pt does not exist",
    ),
    "resume of a plain checkpoint": (
        ["--resume", "{tmp}/init.pt"],
        "error: {tmp}/init.pt is not a training checkpoint of ours",
    ),
}


@pytest.mark.parametrize("case", list(INPUTS))
def test_bad_input(tmp_path: Path, good: list[str], capsys: pytest.CaptureFixture, case: str):
    args, message = INPUTS[case]
    argv = [
        *good,
        "--out",
        str(tmp_path / "out"),
        *(a.replace("{tmp}", str(tmp_path)) for a in args),
    ]
    _fails(argv, 1, message.replace("{tmp}", str(tmp_path)), capsys)
    assert not (tmp_path / "out" / "last.pt").exists()
    assert not (tmp_path / "out" / pair_tune.FINAL).exists()


def test_out_holding_a_run_needs_resume(
    tmp_path: Path, good: list[str], capsys: pytest.CaptureFixture
) -> None:
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "last.pt").write_bytes(b"earlier run")
    message = f"error: {tmp_path}/out holds a run already: pass --resume {tmp_path}/out/last.pt"
    _fails([*good, "--out", str(tmp_path / "out")], 2, message, capsys)
    assert (tmp_path / "out" / "last.pt").read_bytes() == b"earlier run"
    assert not (tmp_path / "out" / "train_log.jsonl").exists()
