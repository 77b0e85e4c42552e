"""Keep an unfinished demo-model run in the repository, small, and bring it back.

A CPU run of scripts/train_demo_model.sh can outlast a sitting (issue 24). ``pack`` stores what
the next sitting needs to continue it: stage one's final weights and stage two's last.pt (weights,
AdamW moments and progress), or stage two's final weights once it has finished (the drive stage
starts from them), the training logs and curves. Weights go to float16 and AdamW
moments to bfloat16 (float16 would flush the smallest second moments to zero); position tables
and step counters stay as they are. ``unpack`` writes them back as float32 files the trainers
read, so re-running the recipe resumes stage two where it stopped:

    python scripts/train_state.py pack /work/demo_train_run train_state/demo-small
    python scripts/train_state.py unpack train_state/demo-small demo_train
    OUT=demo_train bash scripts/train_demo_model.sh
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import torch

CHECKPOINTS = ("stage1/stage1_final.pt", "stage2/stage2_final.pt", "stage2/last.pt")
COPIED = (
    "pretrain/train_log.jsonl",
    "stage1/train_log.jsonl",
    "stage2/train_log.jsonl",
    "stage2/curves.png",
    "pair_tune/train_log.jsonl",
    "curves.png",
)


def _convert(obj: object, key: str, packing: bool) -> object:
    """Tensors of a checkpoint, recursively: float -> fp16 / bf16 (pack) or float32 (unpack)."""
    if isinstance(obj, dict):
        return {k: _convert(v, str(k), packing) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_convert(v, key, packing) for v in obj)
    if not isinstance(obj, torch.Tensor) or not obj.is_floating_point() or obj.ndim == 0:
        return obj
    if not packing:
        return obj.float()
    if "pos_embed" in key:  # fixed tables: kept exact
        return obj
    return obj.to(torch.bfloat16 if key.startswith("exp_avg") else torch.float16)


def pack(out: Path, dest: Path) -> list[Path]:
    """Small copies of ``out``'s resumable state under ``dest``; returns the files written."""
    written = []
    for rel in CHECKPOINTS:
        if rel == "stage2/last.pt" and (out / "stage2" / "stage2_final.pt").is_file():
            continue  # stage two has finished: its final weights are all the next stage needs
        if (out / rel).is_file():
            state = torch.load(out / rel, map_location="cpu", weights_only=True)
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            torch.save(_convert(state, "", True), dest / rel)
            written.append(dest / rel)
    for rel in COPIED:
        if (out / rel).is_file():
            (dest / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(out / rel, dest / rel)
            written.append(dest / rel)
    return written


def unpack(src: Path, out: Path, force: bool = False) -> list[Path]:
    """float32 checkpoints and the logs from ``src`` into ``out`` (a run folder)."""
    written = []
    for rel in (*CHECKPOINTS, *COPIED):
        if not (src / rel).is_file():
            continue
        if (out / rel).exists() and not force:
            raise FileExistsError(f"{out / rel} exists; pass --force to overwrite it")
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        if rel.endswith(".pt"):
            state = torch.load(src / rel, map_location="cpu", weights_only=True)
            torch.save(_convert(state, "", False), out / rel)
        else:
            shutil.copyfile(src / rel, out / rel)
        written.append(out / rel)
    return written


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    a = sub.add_parser("pack", help="run folder -> small state folder")
    a.add_argument("out", type=Path, help="OUT folder of scripts/train_demo_model.sh")
    a.add_argument("dest", type=Path, help="state folder to write (e.g. train_state/demo-small)")
    b = sub.add_parser("unpack", help="small state folder -> run folder")
    b.add_argument("src", type=Path, help="state folder written by pack")
    b.add_argument("out", type=Path, help="OUT folder to continue the recipe in")
    b.add_argument("--force", action="store_true", help="overwrite files already in OUT")
    args = p.parse_args(argv)
    try:
        if args.command == "pack":
            files = pack(args.out, args.dest)
        else:
            files = unpack(args.src, args.out, args.force)
    except (OSError, RuntimeError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    if not files:
        print("error: nothing to copy", file=sys.stderr)
        return 1
    for f in files:
        print(f"wrote {f} ({f.stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
