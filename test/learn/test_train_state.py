"""scripts/train_state.py: an unfinished run packed small (fp16 weights, bf16 AdamW moments) and
unpacked into float32 files the trainers resume from."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch

from pair_vpr_ros.learn.train.common import read_training_state, save_training_checkpoint
from pair_vpr_ros.model import ModelConfig, build_pairvpr, load_pairvpr, save_pairvpr

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "train_state.py"


def _module():  # noqa: ANN202
    spec = importlib.util.spec_from_file_location("train_state", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_pack_and_unpack_a_run(tmp_path: Path) -> None:
    run, packed, back = tmp_path / "run", tmp_path / "packed", tmp_path / "back"
    model = build_pairvpr(ModelConfig.tiny(), seed=0)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    loss = model.encode(torch.randn(2, 3, 56, 56))[1].sum()
    loss.backward()
    opt.step()
    state = {"stage": 2, "epoch": 1, "batch": 3, "step": 21, "config": {"twin_share": 0.25}}
    save_training_checkpoint(model, run / "stage2" / "last.pt", opt, state)
    save_pairvpr(model, run / "stage1" / "stage1_final.pt", extra={"stage": 1})
    (run / "stage2" / "train_log.jsonl").write_text('{"step": 1, "loss": 1.0}\n')
    main = _module().main
    assert main(["pack", str(run), str(packed)]) == 0
    small = torch.load(packed / "stage2" / "last.pt", weights_only=True)
    assert small["model"]["encoder.model.cls_token"].dtype == torch.float16
    assert small["model"]["dec_pos_embed"].dtype == torch.float32  # fixed table kept exact
    moments = next(iter(small["optimizer"]["state"].values()))
    assert moments["exp_avg_sq"].dtype == torch.bfloat16
    size = (packed / "stage2" / "last.pt").stat().st_size
    assert size < (run / "stage2" / "last.pt").stat().st_size
    assert main(["unpack", str(packed), str(back)]) == 0
    assert main(["unpack", str(packed), str(back)]) == 1  # refuses to overwrite
    restored = read_training_state(back / "stage2" / "last.pt")
    assert (restored["step"], restored["config"]) == (21, {"twin_share": 0.25})
    again = load_pairvpr(back / "stage2" / "last.pt")
    for name, value in model.state_dict().items():
        assert torch.allclose(again.state_dict()[name], value, atol=2e-3), name
    assert (back / "stage2" / "train_log.jsonl").read_text() == '{"step": 1, "loss": 1.0}\n'
    assert main(["pack", str(tmp_path / "empty"), str(tmp_path / "p2")]) == 1


def test_a_finished_stage_two_is_packed_as_its_final_weights(tmp_path: Path) -> None:
    run, packed, back = tmp_path / "run", tmp_path / "packed", tmp_path / "back"
    model = build_pairvpr(ModelConfig.tiny(), seed=0)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    save_training_checkpoint(model, run / "stage2" / "last.pt", opt, {"stage": 2, "step": 9})
    save_pairvpr(model, run / "stage2" / "stage2_final.pt", extra={"stage": 2})
    main = _module().main
    assert main(["pack", str(run), str(packed)]) == 0
    assert sorted(p.name for p in (packed / "stage2").iterdir()) == ["stage2_final.pt"]
    assert main(["unpack", str(packed), str(back)]) == 0
    again = load_pairvpr(back / "stage2" / "stage2_final.pt")
    assert again.state_dict()["dec_pos_embed"].dtype == torch.float32
    for name, value in model.state_dict().items():
        assert torch.allclose(again.state_dict()[name], value, atol=2e-3), name
