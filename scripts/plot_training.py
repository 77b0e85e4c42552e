"""Plot training loss curves (train_log.jsonl of either stage) side by side into one PNG:

    python scripts/plot_training.py docs/demo_training.png \\
        "stage two=demo_train/stage2/train_log.jsonl" "grey=demo_train/grey/train_log.jsonl"
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

TERMS = ("loss", "global", "patch", "pair")  # logged terms, drawn when a run has them
CHANCE = 0.6931  # binary cross-entropy of a pair classifier at chance


def read_log(path: Path) -> list[dict]:
    """The step records of one train_log.jsonl (epoch-end validation records left out)."""
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in rows if "loss" in r]


def plot(panels: list[tuple[str, Path]], dest: Path, smooth: int = 5) -> None:
    """One panel per (title, log); each term as a running mean over the last ``smooth``
    records."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.4), squeeze=False)
    for ax, (title, path) in zip(axes[0], panels, strict=True):
        rows = read_log(path)
        if not rows:
            raise ValueError(f"{path} holds no training steps")
        steps = np.array([r["step"] for r in rows])
        for term in TERMS:
            values = np.array([r.get(term, 0.0) for r in rows], dtype=float)
            if not values.any():
                continue
            mean = [values[max(0, i - smooth + 1) : i + 1].mean() for i in range(len(values))]
            ax.plot(steps, mean, label=term, lw=1.2)
        if any(r.get("pair") for r in rows):
            ax.axhline(CHANCE, color="grey", ls=":", lw=1, label="pair at chance")
        ax.set(title=title, xlabel="step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    dest.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(dest, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dest", type=Path, help="PNG to write")
    p.add_argument("logs", nargs="+", metavar="TITLE=LOG", help="panel title and its log file")
    p.add_argument("--smooth", type=int, default=5, help="running mean over N log records")
    args = p.parse_args(argv)
    if args.smooth < 1 or any("=" not in x for x in args.logs):
        p.error("give each log as TITLE=PATH, and --smooth >= 1")
    panels = [(t, Path(f)) for t, f in (x.split("=", 1) for x in args.logs)]
    try:
        plot(panels, args.dest, args.smooth)
    except (OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(f"wrote {args.dest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
