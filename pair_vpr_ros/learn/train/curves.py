"""What training measures on the way: Recall@N on validation sets after each epoch, re-ranked vs
global AP on a held-out place set every ``--eval-every`` steps, and the curves of both as one
PNG (each stage's losses, the ``heldout`` records of stage two and the ``val`` records of the
drive stage, `pair_tune`)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from pair_vpr_ros.learn.eval_sets import load_eval_set
from pair_vpr_ros.learn.heldout import HeldoutViews, measure
from pair_vpr_ros.learn.recall import EvalConfig, evaluate_set
from pair_vpr_ros.model import PairVPR

LOSSES = ("loss", "global", "patch", "pair", "pair_rank")
HELDOUT = (
    "global_ap",
    "rerank_ap",
    "grey_global_ap",
    "grey_rerank_ap",
    "lighting_auc",
    "identical_ge_revisit",
)
# record key -> (metrics drawn, panel title)
EVALS = {
    "heldout": (HELDOUT, "held-out world"),
    "val": (("global", "pair", "rerank_10", "rerank_20", "rerank_40"), "validation drive, AP"),
}
CHANCE = 0.6931  # binary cross-entropy of a pair classifier at chance


def read_records(path: Path) -> tuple[list[dict], list[dict]]:
    """(step records, evaluation records: ``heldout`` or ``val``) of a train_log.jsonl; a
    missing file has neither."""
    if not path.is_file():
        return [], []
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in rows if "loss" in r], [r for r in rows if set(r) & set(EVALS)]


def _mean(values: list[float], n: int) -> list[float]:
    return [sum(values[max(0, i - n + 1) : i + 1]) / len(values[max(0, i - n + 1) : i + 1])
            for i in range(len(values))]  # fmt: skip


def draw_curves(logs: list[tuple[str, Path]], dest: Path, smooth: int = 10) -> Path:
    """One loss panel per (title, train_log.jsonl) with steps, then one held-out panel for the
    logs that have held-out records; written to ``dest``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = [(t, *read_records(p)) for t, p in logs]
    runs = [r for r in runs if r[1]]
    evals = [(t, h) for t, _, h in runs if h]
    panels = len(runs) + len(evals)
    if not panels:
        raise ValueError(f"no training steps logged in {[str(p) for _, p in logs]}")
    fig, axes = plt.subplots(1, panels, figsize=(4.4 * panels, 3.4), squeeze=False)
    axes = list(axes[0])
    for ax, (title, steps, _) in zip(axes, runs, strict=False):
        x = [r["step"] for r in steps]
        for term in LOSSES:
            values = [float(r.get(term, 0.0)) for r in steps]
            if any(values):
                ax.plot(x, _mean(values, smooth), label=term, lw=1.2)
        if any(r.get("pair") for r in steps):
            ax.axhline(CHANCE, color="grey", ls=":", lw=1, label="pair at chance")
        ax.set(title=f"{title}: losses", xlabel="step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax, (title, records) in zip(axes[len(runs) :], evals, strict=True):
        key = next(k for k in EVALS if k in records[0])
        terms, what = EVALS[key]
        x = [r["step"] for r in records if key in r]
        for term in terms:
            y = [r[key].get(term, float("nan")) for r in records if key in r]
            ax.plot(x, y, "o-", label=term)
        ax.axhline(0.5, color="grey", ls=":", lw=1)
        ax.set(title=f"{title}: {what}", xlabel="step", ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    dest.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(dest, dpi=80)
    plt.close(fig)
    return dest


GREY_KEYS = ("global_ap", "rerank_ap")


def heldout_hook(
    model: PairVPR, root: Path | None, every: int, out_dir: Path, k: int = 10
) -> tuple[int, Callable[[int], dict]] | None:
    """(every, step -> held-out metrics) that also redraws ``out_dir/curves.png``; None if off."""
    if root is None or every <= 0:
        return None
    views = HeldoutViews.load(root)

    def run(step: int) -> dict:
        metrics = measure(model, views, k)
        grey = measure(model, views, k, grey=True)  # a mono8 camera: queries and map in grey
        metrics.update({f"grey_{key}": grey[key] for key in GREY_KEYS})
        log = out_dir / "train_log.jsonl"
        try:  # the record of this step is written after this returns: draw the others now
            draw_curves([("stage two", log)], out_dir / "curves.png")
        except (OSError, ValueError) as err:
            print(f"note: curves not drawn: {err}")
        return metrics

    return every, run


def validate(
    model: PairVPR, roots: tuple[Path, ...], rerank_k: int, workers: int
) -> dict[str, dict[str, float]]:
    """Recall@1/5/10 on each validation set (global, and re-ranked if rerank_k > 0)."""
    ecfg = EvalConfig(
        datasets=list(roots),
        rerank_k=rerank_k,
        recall_ns=(1, 5, 10),
        batch_size=32,
        workers=workers,
        progress=False,
    )
    out = {}
    for root in roots:
        r = evaluate_set(model, load_eval_set(root), ecfg)
        out[r.dataset] = {f"R@{n}": v for n, v in r.recall_global.items()}
        out[r.dataset].update({f"rerank R@{n}": v for n, v in r.recall_rerank.items()})
    model.train()
    return out
