"""The learned global floor (`DetectorConfig.learned_floor`, with `rerank_cascade`): a keyframe
whose best global similarity lies far below what this map's accepted loops had is not re-ranked.

Accepted loops tell what a revisit looks like to the global descriptor: the similarity of their
keyframe's best global candidate. The floor is the `QUANTILE` of the last `WINDOW` of them less
`MARGIN` (cosine); a keyframe below it cannot be a loop in all likelihood, and its 2K decoder
passes are saved. Young: while fewer than `MIN_LOOPS` loops were accepted since the map was
made, loaded or cleared, there is no floor and nothing is skipped. Nor is a keyframe that may
continue the previous keyframe's loop (`sequence_margin`): the views between two confident
matches are the low-similarity revisits the margin is for. The benchmark
(benchmarks/bench_rerank_budget.py) counts the keyframes skipped and the loops that cost.
"""

from __future__ import annotations

from collections import deque

import numpy as np

MIN_LOOPS = 50  # accepted loops before the floor applies: a young map skips nothing
QUANTILE = 0.01  # of the accepted loops' best global similarity
MARGIN = 0.05  # cosine below that quantile
WINDOW = 10_000  # the most recent accepted loops the floor is learned from


class LearnedFloor:
    """The accepted loops' best global similarities and the floor they give."""

    def __init__(self) -> None:
        self._seen: deque[float] = deque(maxlen=WINDOW)

    def reset(self) -> None:
        """A new, loaded or cleared map: young again."""
        self._seen.clear()

    def accepted(self, best_similarity: float) -> None:
        """A loop was accepted at a keyframe whose best global similarity is this."""
        self._seen.append(float(best_similarity))

    @property
    def loops(self) -> int:
        return len(self._seen)

    def value(self) -> float | None:
        """The floor, or None while the map is young."""
        if len(self._seen) < MIN_LOOPS:
            return None
        return float(np.quantile(np.fromiter(self._seen, float), QUANTILE)) - MARGIN
