"""What a replay decided, keyframe by keyframe, kept compactly for after the run: each queried
keyframe's top-K candidates with their scores, and what verification and the relative pose said
about the candidates they saw. The report labels the candidates from it, and `what_if` decides
again from it with other thresholds (the threshold suggestion).

Memory: about 50 bytes a candidate in typed arrays (K = 10: ~0.5 KB a keyframe, 50 MB for
100,000 keyframes), plus one small entry per verified or posed candidate.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterator
from dataclasses import dataclass

from pair_vpr_ros.loops.frames import FrameOutcome
from pair_vpr_ros.loops.records import Candidate


@dataclass(frozen=True)
class LoggedKeyframe:
    """One queried keyframe: its row (order of decision), map id (-1: not stored), stamp,
    frame id, whether a new session started before it, whether the maps were searched
    (False: no map had an eligible keyframe or the map did not answer), its candidates in
    global order with their logged pair scores (NaN: not scored)."""

    row: int
    map_id: int
    stamp: float
    frame_id: str
    new_session: bool
    searched: bool
    candidates: list[Candidate]


class DecisionLog:
    """Append `FrameOutcome`s as they come (`add`); read keyframes back (`keyframes`)."""

    def __init__(self) -> None:
        self._names: dict[str, int] = {}  # frame ids, robots and sessions, interned
        self._name_list: list[str] = []
        self.map_id, self.stamp = array("q"), array("d")
        self.frame, self.flags, self.start = array("i"), array("b"), array("q", [0])
        self.c_id, self.c_stamp, self.c_frame = array("q"), array("d"), array("i")
        self.c_robot, self.c_session, self.c_prior = array("i"), array("i"), array("i")
        self.c_sim, self.c_rank, self.c_score = array("d"), array("i"), array("d")
        # (row, rank_before) -> (inliers, inlier ratio) / pose status, as the run found them
        self.verified: dict[tuple[int, int], tuple[int, float]] = {}
        self.posed: dict[tuple[int, int], str] = {}
        self.accepted: list[tuple[int, int]] = []  # (row, rank_before) the run accepted
        self._jump = False

    def __len__(self) -> int:
        return len(self.stamp)

    def _name(self, text: str) -> int:
        if text not in self._names:
            self._names[text] = len(self._name_list)
            self._name_list.append(text)
        return self._names[text]

    def add(self, outcome: FrameOutcome) -> int | None:
        """Log `outcome` (every outcome, in order: a clock jump may come on a skipped frame);
        -> its row, None when the frame was no keyframe."""
        self._jump = self._jump or outcome.clock_jump_s > 0
        if outcome.skipped:
            return None
        row = len(self.stamp)
        map_id = outcome.keyframe_id if outcome.keyframe_id is not None else -1
        self.map_id.append(map_id)
        self.stamp.append(outcome.stamp)
        decisions = outcome.decisions()
        self.frame.append(self._name(decisions[0].query_frame_id if decisions else ""))
        searched = "search" in outcome.timings_ms  # set once the maps answered (pipeline)
        self.flags.append(int(self._jump) | 2 * int(searched))
        self._jump = False
        for c in outcome.candidates:
            self.c_id.append(c.id)
            self.c_stamp.append(c.stamp)
            self.c_frame.append(self._name(c.frame_id))
            self.c_robot.append(self._name(c.robot))
            self.c_session.append(self._name(c.session))
            self.c_prior.append(c.prior)
            self.c_sim.append(c.global_similarity)
            self.c_rank.append(c.rank_before)
            self.c_score.append(c.pair_score)
        self.start.append(len(self.c_id))
        for record in decisions:
            key = (row, record.rank_before)
            if record.inliers >= 0 or record.reason.startswith("geometric verification"):
                self.verified[key] = (record.inliers, record.inlier_ratio)
            if record.accepted:
                self.accepted.append(key)
                self.posed[key] = record.pose_status
        return row

    def candidates(self, row: int) -> list[Candidate]:
        """The candidates of keyframe `row`, new objects (global order, logged scores)."""
        name = self._name_list
        return [
            Candidate(
                self.c_id[i],
                self.c_stamp[i],
                name[self.c_frame[i]],
                self.c_sim[i],
                self.c_rank[i],
                self.c_score[i],
                robot=name[self.c_robot[i]],
                session=name[self.c_session[i]],
                prior=self.c_prior[i],
            )  # fmt: skip
            for i in range(self.start[row], self.start[row + 1])
        ]

    def keyframe(self, row: int) -> LoggedKeyframe:
        flags = self.flags[row]
        return LoggedKeyframe(
            row, self.map_id[row], self.stamp[row], self._name_list[self.frame[row]],
            bool(flags & 1), bool(flags & 2), self.candidates(row),
        )  # fmt: skip

    def keyframes(self) -> Iterator[LoggedKeyframe]:
        for row in range(len(self)):
            yield self.keyframe(row)

    def score_of(self, row: int, rank_before: int) -> float:
        """The logged pair score of one candidate (NaN: not scored, or no such candidate)."""
        for i in range(self.start[row], self.start[row + 1]):
            if self.c_rank[i] == rank_before:
                return self.c_score[i]
        return math.nan
