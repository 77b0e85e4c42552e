"""Export the demo recipe's final weights as the shipped demo model: float16 tensors (half the
size; the loader casts them back to float32), the architecture, and a summary of the training
logs. The final weights are stage two on drives' (pair_tune/pair_tune_final.pt) when that stage
ran, else stage two's (stage2/stage2_final.pt); the summary names which.

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


STAGE2_KEYS = (
    "max_steps", "places_per_batch", "lr", "conditions", "twin_share", "grey", "grey_places",
)  # fmt: skip
PAIR_TUNE_KEYS = (
    "steps", "batch", "twins", "lonely", "lr", "weight_decay", "top_k", "exclude_recent_s",
    "exclude_recent_keyframes", "gt_radius", "negative_radius", "seed", "drive", "val",
)  # fmt: skip


def stage_config(path: Path, keys: tuple[str, ...]) -> dict:
    """The settings of a stage that shape the pair classifier, from its last.pt (or {})."""
    if not path.is_file():
        return {}
    config = torch.load(path, map_location="cpu", weights_only=True).get("config", {})
    return {k: config[k] for k in keys if k in config}


def val_records(path: Path) -> dict:
    """The first and last validation records ({"step", "val"}) of a pair-tune log: before
    tuning (step 0) and at its last measurement; {} without any."""
    if not path.is_file():
        return {}
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    rows = [r for r in rows if "val" in r]
    return {"first": rows[0], "last": rows[-1]} if rows else {}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("train_dir", type=Path, help="the OUT folder of scripts/train_demo_model.sh")
    p.add_argument("dest", type=Path, help="where to write the .pth (a .json summary goes beside)")
    args = p.parse_args(argv)
    tuned = args.train_dir / "pair_tune" / "pair_tune_final.pt"
    source = tuned if tuned.is_file() else args.train_dir / "stage2" / "stage2_final.pt"
    model = load_pairvpr(source)
    state = {k: v.half() if v.is_floating_point() else v for k, v in model.state_dict().items()}
    args.dest.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": state, "arch": model.config.to_dict(), "format": FORMAT}, args.dest)
    summary = {
        "file": args.dest.name,
        "size_bytes": args.dest.stat().st_size,
        "parameters": sum(v.numel() for v in state.values()),
        "arch": model.config.to_dict(),
        "recipe": "scripts/train_demo_model.sh",
        "weights_from": str(source.relative_to(args.train_dir)),
        "pretrain": log_summary(args.train_dir / "pretrain" / "train_log.jsonl"),
        "stage1": log_summary(args.train_dir / "stage1" / "train_log.jsonl"),
        "stage2": log_summary(args.train_dir / "stage2" / "train_log.jsonl"),
        "stage2_config": stage_config(args.train_dir / "stage2" / "last.pt", STAGE2_KEYS),
    }
    if source == tuned:
        tune = args.train_dir / "pair_tune"
        summary["pair_tune"] = log_summary(tune / "train_log.jsonl")
        summary["pair_tune_config"] = stage_config(tune / "last.pt", PAIR_TUNE_KEYS)
        summary["pair_tune_val"] = val_records(tune / "train_log.jsonl")
    args.dest.with_suffix(".json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"wrote {args.dest} ({summary['size_bytes'] / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
