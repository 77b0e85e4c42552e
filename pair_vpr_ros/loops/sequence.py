"""What a loop detector remembers from one query to the next, per track (the map a decision is
about with `loop_per_map`, else None): its recent matches, for `temporal_consistency`, and the
previous query's accepted loop, for `sequence_margin`.

Why a sequence margin: a robot revisiting a place passes its keyframes in order, and the views
between two confident matches can score lower (other light, a few metres aside, a turn) yet be
the same place. A candidate that continues the last accepted loop (same map, robot and session;
id within `temporal_tolerance`) is accepted at `score_threshold - sequence_margin`; geometric
verification still applies, and a query without an accepted loop ends the sequence.
"""

from __future__ import annotations

from collections import deque
from typing import Any


def track_of(candidate: Any, loop_per_map: bool) -> int | None:
    """The track a decision about `candidate` counts in: its map (`prior`) when each map
    decides on its own (`loop_per_map`), else the one stream of decisions (None)."""
    return candidate.prior if loop_per_map else None


class DecisionTracks:
    """Per-track memory of a `LoopDetector`; `config` is its `DetectorConfig`.
    Candidates are `detector.Candidate` (`group`, `id`, `rerank_score`)."""

    def __init__(self, config: Any) -> None:
        self.config = config
        self._recent: dict[int | None, deque[tuple]] = {}
        self._followed: dict[int | None, tuple] = {}

    def reset(self) -> None:
        self._recent.clear()
        self._followed.clear()

    def set_config(self, config: Any) -> None:
        """New settings; the recent matches kept, up to the new `temporal_consistency`."""
        self.config = config
        n = config.temporal_consistency
        self._recent = {key: deque(old, maxlen=n) for key, old in self._recent.items()}

    def recent(self, track: int | None) -> deque[tuple]:
        if track not in self._recent:
            self._recent[track] = deque(maxlen=self.config.temporal_consistency)
        return self._recent[track]

    def consistent(self, track: int | None, match: Any) -> bool:
        """Count `match`; True once `temporal_consistency` recent matches agree: matches of one
        map, robot and session whose ids lie within `temporal_tolerance` (ids of different
        robots or sessions say nothing about place)."""
        recent = self.recent(track)
        if recent and not self._continues(recent[-1], match):
            recent.clear()
        recent.append((match.group, match.id))
        return len(recent) >= self.config.temporal_consistency

    def follower(self, track: int | None, scored: list) -> tuple[int, Any] | None:
        """(rank, candidate): the best-scored of `scored` (best first) that continues the
        previous query's accepted loop and scores >= score_threshold - sequence_margin; None
        when none does, or the margin is 0."""
        c = self.config
        if c.sequence_margin <= 0 or track not in self._followed:
            return None
        last, floor = self._followed[track], c.score_threshold - c.sequence_margin
        for rank, cand in enumerate(scored, 1):
            if self._continues(last, cand) and cand.rerank_score(c.global_weight) >= floor:
                return rank, cand
        return None

    def follow_goal(self, track: int | None) -> tuple[float | None, Any]:
        """(floor, continues): what `follower` would accept, for the re-rank cascade: the
        lower floor and whether a candidate continues the previous loop; (None, never) when
        there is no sequence to follow."""
        c = self.config
        if c.sequence_margin <= 0 or track not in self._followed:
            return None, lambda cand: False
        last = self._followed[track]
        return c.score_threshold - c.sequence_margin, lambda cand: self._continues(last, cand)

    def _continues(self, last: tuple, match: Any) -> bool:
        """`match` agrees with the earlier match `last` (group, id): the same map, robot and
        session, its id within `temporal_tolerance`."""
        group, last_id = last
        return match.group == group and abs(match.id - last_id) <= self.config.temporal_tolerance

    def decided(self, track: int | None, match: Any, accepted: bool) -> None:
        """Remember the accepted loop to `match`, or end the sequence."""
        if accepted and match is not None:
            self._followed[track] = (match.group, match.id)
        else:
            self._followed.pop(track, None)
