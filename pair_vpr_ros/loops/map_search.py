"""The maps one query searches: the pipeline's live map and read-only prior maps, as one.

Each map is searched with its own FAISS index for the top-K ids it may give (recent keyframes
of the query's own robot and session left out, `recency.GroupedRecency`); the hits of all maps
are merged by global similarity into one top-K list of `Candidate` s (`search`), or kept as one
top-K list per map (`search_each`, for `DetectorConfig.loop_per_map`), each candidate knowing
its map (`Candidate.prior`: -1 live, i >= 0 the i-th prior map). Re-ranking reads every candidate's
dense tokens from its own map, so a prior map's keyframes are scored with their own tokens.
Prior maps are never written: they are loaded with `read_only=True` and closed by their owner.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.recency import GroupedRecency
from pair_vpr_ros.loops.records import Candidate
from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.milvus.expr import Exclusion


def recency_of(place_map: PlaceMap) -> GroupedRecency:
    """The stamps of `place_map`'s keyframes by robot-session."""
    return GroupedRecency((m.id, m.stamp, m.robot, m.session) for m in place_map.all_meta())


class MapSearch:
    """Top-K search over a live map and prior maps with per-robot-session recency."""

    def __init__(self, live: PlaceMap, priors: Sequence[PlaceMap] = ()) -> None:
        self.priors = list(priors)
        self._prior_recency = [recency_of(m) for m in self.priors]
        self.reset(live)

    def reset(self, live: PlaceMap) -> None:
        """Follow a new (or cleared, or loaded) live map."""
        self.live = live
        self._recency = recency_of(live)

    def added(self, meta: KeyframeMeta) -> None:
        """Note a keyframe just added to the live map (`meta.id` set)."""
        self._recency.append(meta.id, meta.stamp, meta.robot, meta.session)

    def map_of(self, cand: Candidate) -> PlaceMap:
        return self.live if cand.prior < 0 else self.priors[cand.prior]

    def search(
        self, desc: np.ndarray, stamp: float, who: Identity, config: DetectorConfig
    ) -> list[Candidate] | None:
        """The top-`config.top_k` candidates of all maps, best global similarity first (ties:
        the live map, then prior maps in order); None when no map has an eligible keyframe."""
        hits = self._hits(desc, stamp, who, config)
        if hits is None:
            return None
        return [self._candidate(*hit, rank) for rank, hit in enumerate(hits[: config.top_k], 1)]

    def search_each(
        self, desc: np.ndarray, stamp: float, who: Identity, config: DetectorConfig
    ) -> list[list[Candidate]] | None:
        """The top-`config.top_k` candidates of each map on its own (`loop_per_map`): one list
        per map with hits, live map first, each best global similarity first. `rank_before`
        counts over all of them (by similarity, ties as `search`), so it names one candidate
        of the keyframe. None when no map has an eligible keyframe."""
        hits = self._hits(desc, stamp, who, config)
        if hits is None:
            return None
        groups: dict[int, list[Candidate]] = {}
        for rank, hit in enumerate(hits, start=1):
            groups.setdefault(hit[1], []).append(self._candidate(*hit, rank))
        return [groups[prior] for prior in sorted(groups)]

    def _hits(
        self, desc: np.ndarray, stamp: float, who: Identity, config: DetectorConfig
    ) -> list[tuple[float, int, int]] | None:
        """Each map's top-`config.top_k` as (similarity, map, id), all maps together, best
        first (ties: the live map, then prior maps in order); None: no eligible keyframe."""
        hits: list[tuple[float, int, int]] = []  # (similarity, map, id)
        found = False
        recencies = [self._recency, *self._prior_recency]
        for number, (place_map, recency) in enumerate(zip(self.maps, recencies, strict=True)):
            ok = recency.eligible(
                stamp, who.robot, who.session, config.exclude_recent_s,
                config.exclude_recent_keyframes,
            )  # fmt: skip
            if ok is None:
                continue
            found = True
            if place_map.filters_in_index:  # Milvus: the same rules as a filter expression
                limit = recency.own_limit(who.robot, who.session, config.exclude_recent_keyframes)
                rule = Exclusion(stamp, config.exclude_recent_s, limit, who.robot, who.session)
                got = place_map.search(desc, config.top_k, exclusion=rule)
            elif ok.prefix is not None:
                got = place_map.search(desc, config.top_k, max_id=ok.prefix - 1)
            else:
                got = place_map.search(desc, config.top_k, allowed=ok.mask, exclude=ok.exclude)
            hits += [(sim, number - 1, kf_id) for kf_id, sim in got]
        if not found:
            return None
        hits.sort(key=lambda h: (-h[0], h[1]))  # stable: FAISS's order within one map
        return hits

    @property
    def maps(self) -> list[PlaceMap]:
        """The live map, then the prior maps."""
        return [self.live, *self.priors]

    def _candidate(self, sim: float, prior: int, kf_id: int, rank: int) -> Candidate:
        meta = (self.live if prior < 0 else self.priors[prior]).meta(kf_id)
        return Candidate(
            kf_id, meta.stamp, meta.frame_id, float(sim), rank,
            robot=meta.robot, session=meta.session, prior=prior, camera=meta.camera,
        )  # fmt: skip

    def dense(self, cands: Sequence[Candidate]) -> np.ndarray:
        """Dense tokens [K, N, D] float16 of `cands`, each read from its own map."""
        if all(c.prior < 0 for c in cands):
            return self.live.get_dense([c.id for c in cands])
        out = None
        for prior in sorted({c.prior for c in cands}):
            rows = [i for i, c in enumerate(cands) if c.prior == prior]
            part = self.map_of(cands[rows[0]]).get_dense([cands[i].id for i in rows])
            if out is None:
                out = np.empty((len(cands), *part.shape[1:]), dtype=part.dtype)
            out[rows] = part
        return out

    def near(self, match: Candidate, span: int) -> tuple[KeyframeMeta, list[KeyframeMeta]]:
        """(the match's metadata, that of the keyframes of its map, robot, session and camera
        within `span` ids of it: recorded just before or after it)."""
        place_map = self.map_of(match)
        ids = [i for i in range(match.id - span, match.id + span + 1)
               if i != match.id and 0 <= i < len(place_map)]  # fmt: skip
        near = [m for m in map(place_map.meta, ids)
                if (m.robot, m.session, m.camera) == (*match.group[1:], match.camera)]  # fmt: skip
        return place_map.meta(match.id), near

    def close_priors(self) -> None:
        for place_map in self.priors:
            place_map.close()
