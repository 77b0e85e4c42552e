"""Export a stage-two checkpoint as the shipped demo model: float16 tensors (half the size; the
loader casts them back to float32), the architecture, and a summary of both training logs.

    python scripts/export_demo_model.py demo_train pair_vpr_ros/demo/assets/demo-small.pth
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from pair_vpr_ros.model import load_pairvpr
from pair_vpr_ros.model.checkpoint import FORMAT


def log_summary(path: Path) -> dict:
    if not path.is_file():
        return {}
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    rows = [r for r in rows if "loss" in r]  # held-out records carry no loss
    if not rows:
        return {}
    head, tail = rows[: max(1, len(rows) // 10)], rows[-max(1, len(rows) // 10) :]
    mean = lambda rs: round(sum(r["loss"] for r in rs) / len(rs), 4)  # noqa: E731
    return {
        "steps": rows[-1]["step"],
        "loss_first_10pct": mean(head),
        "loss_last_10pct": mean(tail),
    }


def stage2_config(path: Path) -> dict:
    """The stage-two settings that shape the pair classifier, from its last.pt (or {})."""
    if not path.is_file():
        return {}
    config = torch.load(path, map_location="cpu", weights_only=True).get("config", {})
    keys = ("max_steps", "places_per_batch", "lr", "conditions", "twin_share", "grey")
    return {k: config[k] for k in keys if k in config}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("train_dir", type=Path, help="the OUT folder of scripts/train_demo_model.sh")
    p.add_argument("dest", type=Path, help="where to write the .pth (a .json summary goes beside)")
    args = p.parse_args(argv)
    model = load_pairvpr(args.train_dir / "stage2" / "stage2_final.pt")
    state = {k: v.half() if v.is_floating_point() else v for k, v in model.state_dict().items()}
    args.dest.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": state, "arch": model.config.to_dict(), "format": FORMAT}, args.dest)
    summary = {
        "file": args.dest.name,
        "size_bytes": args.dest.stat().st_size,
        "parameters": sum(v.numel() for v in state.values()),
        "arch": model.config.to_dict(),
        "recipe": "scripts/train_demo_model.sh",
        "pretrain": log_summary(args.train_dir / "pretrain" / "train_log.jsonl"),
        "stage1": log_summary(args.train_dir / "stage1" / "train_log.jsonl"),
        "stage2": log_summary(args.train_dir / "stage2" / "train_log.jsonl"),
        "stage2_config": stage2_config(args.train_dir / "stage2" / "last.pt"),
    }
    args.dest.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"wrote {args.dest} ({summary['size_bytes'] / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
