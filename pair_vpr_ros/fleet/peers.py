"""Other robots' keyframe descriptors, searched in this robot's process, and the per-period
budget that bounds how many score requests (each carrying ~0.8 MB of dense tokens) go out.

`PeerStore` (fleet_peer_search "broadcast", the default): one `DescriptorIndex` (exact inner
product) holds every peer keyframe heard; row i belongs to `owners[i]` (robot, session) and is
that robot's keyframe `keyframe_ids[i]`. `SharedPeers` (fleet_peer_search "milvus"): the peers'
rows are already in the Milvus collection this robot's map shares with them, so they are found
there (place_map/milvus/peers.py) and nothing is kept or broadcast.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from pair_vpr_ros.errors import ConfigError, FleetMessageError, MapError
from pair_vpr_ros.fleet.messages import KeyframeDescriptor
from pair_vpr_ros.place_map.index import DescriptorIndex

NORM_TOLERANCE = 0.01  # float16 rounding moves |desc| by ~1e-3; more means not L2-normalised


@dataclass(frozen=True)
class PeerHit:
    """One peer keyframe found for a query: its owner, its id in the owner's map, similarity."""

    robot: str
    session: str
    keyframe_id: int
    stamp: float
    similarity: float


class PeerStore:
    """Descriptors heard from other robots (never this robot's own)."""

    def __init__(self, robot: str, dim: int, tag: bytes, peers: tuple[str, ...] = ()) -> None:
        self.robot, self.dim, self.tag, self.peers = robot, int(dim), tag, tuple(peers)
        self.index = DescriptorIndex(self.dim)
        self.rows: list[tuple[str, str, int, float]] = []  # (robot, session, kf id, stamp)
        self._seen: set[tuple[str, str, int]] = set()
        self._newest: dict[tuple[str, str], int] = {}
        self._count: Counter[tuple[str, str]] = Counter()
        self.reordered = 0  # arrived after a newer keyframe of the same robot-session (kept)
        self.skipped = 0  # searches that could not be made (SharedPeers only)

    def __len__(self) -> int:
        return len(self.rows)

    def check(self, msg: KeyframeDescriptor) -> None:
        """FleetMessageError (with the reason it is counted under) when `msg` cannot be kept."""
        if msg.model != self.tag:
            raise FleetMessageError("wrong model", f"descriptor of robot {msg.robot!r}")
        if msg.robot == self.robot:
            raise FleetMessageError("own robot", f"a descriptor names this robot {msg.robot!r}")
        if self.peers and msg.robot not in self.peers:
            raise FleetMessageError("unknown robot", f"{msg.robot!r} is not in fleet_peers")
        if len(msg.descriptor) != self.dim:
            raise FleetMessageError("wrong size", f"{len(msg.descriptor)}-d, not {self.dim}-d")
        norm = float(np.linalg.norm(msg.descriptor.astype(np.float32)))
        if abs(norm - 1.0) > NORM_TOLERANCE:
            raise FleetMessageError("not normalised", f"|descriptor| = {norm:.3f}")
        if (msg.robot, msg.session, msg.keyframe_id) in self._seen:
            raise FleetMessageError("duplicate", f"{msg.robot}/{msg.session}#{msg.keyframe_id}")

    def add(self, msg: KeyframeDescriptor) -> None:
        """Keep a peer keyframe (checked first: FleetMessageError). A keyframe older than one
        already heard is kept too (the map needs no order) and counted in `reordered`."""
        self.check(msg)
        key = (msg.robot, msg.session)
        if msg.keyframe_id < self._newest.get(key, -1):
            self.reordered += 1
        self._newest[key] = max(self._newest.get(key, -1), msg.keyframe_id)
        self._count[key] += 1
        self._seen.add((msg.robot, msg.session, msg.keyframe_id))
        desc = msg.descriptor.astype(np.float32)
        self.index.add(desc / np.linalg.norm(desc))
        self.rows.append((msg.robot, msg.session, msg.keyframe_id, msg.stamp))

    def missing(self) -> int:
        """Keyframes never heard (gaps in each robot-session's ids 0..newest): lost messages, or
        keyframes a peer made before this robot listened."""
        return sum(self._newest[key] + 1 - self._count[key] for key in self._newest)

    def owners(self) -> dict[str, int]:
        """{"robot/session": keyframes held}."""
        return {f"{r}/{s}": n for (r, s), n in sorted(self._count.items())}

    def search(self, desc: np.ndarray, k: int, floor: float) -> dict[tuple[str, str], list]:
        """desc [dim] -> the `k` most similar peer keyframes with similarity >= `floor`,
        grouped by owner (robot, session): {owner: [PeerHit], best first}, owners in the order
        of their best hit."""
        ids, sims = self.index.search(desc, k)
        out: dict[tuple[str, str], list[PeerHit]] = defaultdict(list)
        for i, sim in zip(ids.tolist(), sims.tolist(), strict=True):
            if sim >= floor:
                robot, session, kf_id, stamp = self.rows[i]
                out[(robot, session)].append(PeerHit(robot, session, kf_id, stamp, sim))
        return dict(out)


class SharedPeers:
    """fleet_peer_search "milvus": other robots' keyframes searched in the Milvus collection
    that the place map `place_map()` (the pipeline's current one) shares with them."""

    def __init__(self, robot: str, place_map: Callable[[], Any], peers: tuple[str, ...] = ()):
        self.robot, self.place_map, self.peers = robot, place_map, tuple(peers)
        self.reordered = 0
        self.skipped = 0  # searches skipped: Milvus did not answer
        self._found: Counter[tuple[str, str]] = Counter()  # hits passed on, per owner

    def __len__(self) -> int:
        return 0  # nothing is kept here

    def add(self, msg: KeyframeDescriptor) -> None:
        raise FleetMessageError(
            "not kept", f"descriptor of {msg.robot!r}: fleet_peer_search is milvus here"
        )

    def missing(self) -> int:
        return 0

    def owners(self) -> dict[str, int]:
        """{"robot/session": candidates found and passed on}."""
        return {f"{r}/{s}": n for (r, s), n in sorted(self._found.items())}

    def search(self, desc: np.ndarray, k: int, floor: float) -> dict[tuple[str, str], list]:
        """As `PeerStore.search`, in the shared collection; {} (counted in `skipped`) when
        Milvus does not answer (or a map of another kind was loaded since)."""
        try:
            rows = self.place_map().search_peers(desc, k, self.robot, self.peers)
        except MapError:
            self.skipped += 1
            return {}
        out: dict[tuple[str, str], list[PeerHit]] = defaultdict(list)
        for row in rows:
            if row.similarity >= floor:
                hit = PeerHit(row.robot, row.session, row.keyframe_id, row.stamp, row.similarity)
                out[(row.robot, row.session)].append(hit)
                self._found[(row.robot, row.session)] += 1
        return dict(out)


PEER_SEARCHES = ("broadcast", "milvus")


def peer_store(config: Any, dim: int, tag: bytes, place_map: Callable[[], Any]):
    """The store a FleetConfig's `peer_search` asks for: PeerStore or SharedPeers."""
    if config.peer_search == "milvus":
        if not place_map().filters_in_index:
            raise ConfigError(
                "fleet_peer_search milvus searches the Milvus collection the robots' maps "
                f"share, but robot {config.robot!r}'s place map is of index kind "
                f"{place_map().index_config.kind!r}: set index to milvus with one milvus_uri "
                "and milvus_collection for every robot, or fleet_peer_search to broadcast"
            )
        return SharedPeers(config.robot, place_map, config.peers)
    return PeerStore(config.robot, dim, tag, config.peers)


@dataclass(frozen=True)
class Proposal:
    """A score request to be: own keyframe `query_id` against `hits` of one owner."""

    similarity: float  # the best hit's: what "best" selection ranks by
    query_id: int
    query_stamp: float
    owner: tuple[str, str]  # (robot, session)
    hits: list[PeerHit]


SELECTIONS = ("best", "first")


class RequestBudget:
    """At most `budget` score requests per `period_s` (Swarm-SLAM's inter-robot loop-closure
    budget per detection period). "first": proposals go out at once while the period's budget
    lasts. "best": a period's proposals are held and, when it ends, the `budget` most similar
    go out (up to one period later; fewer false and more true loops under a tight budget). A
    clock that goes back ends the period."""

    def __init__(self, budget: int, period_s: float, select: str = "best") -> None:
        self.budget, self.period_s, self.select = int(budget), float(period_s), select
        self._start: float | None = None
        self._used = 0
        self._held: list[Proposal] = []

    def _over(self, now: float) -> bool:
        return self._start is not None and (
            now < self._start or now - self._start >= self.period_s
        )

    def offer(self, now: float, proposals: list[Proposal]) -> tuple[list[Proposal], int]:
        """Proposals made at `now` (s) -> (those to send now, how many the budget cut)."""
        if self.select == "first":
            if self._start is None or self._over(now):
                self._start, self._used = now, 0
            send = proposals[: max(self.budget - self._used, 0)]
            self._used += len(send)
            return send, len(proposals) - len(send)
        out: tuple[list[Proposal], int] = ([], 0)
        if self._over(now):
            out = self.flush()
        if self._start is None:
            self._start = now
        self._held += proposals
        return out

    def flush(self) -> tuple[list[Proposal], int]:
        """End the period now: (the held proposals to send, best first; how many cut)."""
        held = sorted(self._held, key=lambda p: -p.similarity)
        self._held, self._start = [], None
        return held[: self.budget], max(len(held) - self.budget, 0)
