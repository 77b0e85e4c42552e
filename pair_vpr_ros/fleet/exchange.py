"""`FleetExchange`: one robot's side of the fleet exchange, ROS-free and transport-free.

It wraps the robot's `LoopClosurePipeline` and talks through `send(Outgoing)` and
`receive(channel, bytes)`; the node maps channels to topics, `fleet.local.LocalBus` connects
exchanges in one process. Per own keyframe: publish its descriptor (~1.1 KB), search the peers'
descriptors, and send a score request (the query's dense tokens) to the owner of candidates
that pass the detector's global floor, within the request budget. Per request received: score
it (`owner.score_request`), answer, and return the inter-robot loop for publishing. Every
message that cannot be used is counted under its reason in `counts.skipped`; none raises.

Not thread-safe: drive it on the pipeline's thread (it reads the pipeline's map).
"""

from __future__ import annotations

import math
import secrets
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, fields

from pair_vpr_ros.errors import ConfigError, FleetMessageError, PairVPRError
from pair_vpr_ros.fleet.messages import (
    KeyframeDescriptor,
    Message,
    ScoreRequest,
    ScoreResponse,
    check,
    decode,
)
from pair_vpr_ros.fleet.messages import encode as encode_message
from pair_vpr_ros.fleet.owner import InterRobotLoop, check_own_keyframes, score_request
from pair_vpr_ros.fleet.peers import PEER_SEARCHES, SELECTIONS, Proposal, RequestBudget, peer_store
from pair_vpr_ros.fleet.wire import model_tag
from pair_vpr_ros.identity import name_problem
from pair_vpr_ros.loops.frames import FrameOutcome
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline

CHANNELS = {"keyframes": KeyframeDescriptor, "request": ScoreRequest, "response": ScoreResponse}
REMEMBERED = 4096  # request ids remembered for duplicate / late detection


@dataclass(frozen=True)
class FleetConfig:
    """robot / session: this robot's identity; budget: score requests per period_s (0: send
    descriptors only); top_k: peer keyframes searched per own keyframe; timeout_s: a request
    unanswered this long is counted lost; peers: robots listened to (empty: any);
    send_features: add the query's keyframe features to requests (owner computes the pose);
    select: "best" (a period's most similar candidates, sent when it ends) or "first" (sent
    at once while the budget lasts), see peers.RequestBudget; peer_search: "broadcast" (publish
    descriptors, search those heard) or "milvus" (search the peers' rows in the Milvus
    collection the robots' maps share; no descriptor is published)."""

    robot: str
    session: str
    budget: int = 4
    period_s: float = 10.0
    top_k: int = 3
    timeout_s: float = 10.0
    peers: tuple[str, ...] = ()
    send_features: bool = True
    select: str = "best"
    peer_search: str = "broadcast"

    def __post_init__(self) -> None:
        names = [("fleet robot", self.robot), ("fleet session", self.session)]
        for what, name in names + [("fleet_peers robot", p) for p in self.peers]:
            problem = name_problem(what, name)
            if problem:
                raise ConfigError(problem)
        checks = {
            "budget": self.budget >= 0,
            "top_k": 1 <= self.top_k <= 64,
            "period_s": math.isfinite(self.period_s) and self.period_s > 0,
            "timeout_s": math.isfinite(self.timeout_s) and self.timeout_s > 0,
            "select": self.select in SELECTIONS,
            "peer_search": self.peer_search in PEER_SEARCHES,
        }
        for name, ok in checks.items():
            if not ok:
                raise ConfigError(f"fleet {name}={getattr(self, name)!r} is out of range")
        if self.robot in self.peers:
            raise ConfigError(
                f"fleet_peers {list(self.peers)} name this robot {self.robot!r}: list the other "
                "robots it listens to ('' = any robot)"
            )


@dataclass(frozen=True)
class Outgoing:
    channel: str  # "keyframes", "request" or "response"
    target: str  # the owner robot of a request; "" = every robot
    data: bytes  # the codec's bytes
    message: Message | None = None  # the same message decoded (a typed transport sends this)


@dataclass
class FleetCounts:
    keyframes: int = 0  # own keyframes whose descriptor was published
    sent: Counter = field(default_factory=Counter)  # channel -> messages
    sent_bytes: Counter = field(default_factory=Counter)  # channel -> bytes
    received: Counter = field(default_factory=Counter)
    received_bytes: Counter = field(default_factory=Counter)
    skipped: Counter = field(default_factory=Counter)  # reason -> messages not used
    ignored: int = 0  # own descriptors heard back, responses meant for other robots
    budget_cut: int = 0  # requests not sent: the period's budget was spent
    query_gone: int = 0  # selected requests whose query keyframe left the map before sending
    timeouts: int = 0  # requests unanswered within timeout_s
    loops_accepted: int = 0  # inter-robot loops this robot accepted as owner
    loops_rejected: int = 0  # requests this robot scored as owner without accepting
    loops_confirmed: int = 0  # own requests answered "accepted" by the owner

    def summary(self) -> dict:
        """Counts plus bytes per own keyframe and per accepted loop (requester side)."""
        # not dataclasses.asdict: it rebuilds a Counter from (key, value) pairs, counting pairs
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out = {k: dict(v) if isinstance(v, Counter) else v for k, v in out.items()}
        kf, total = self.keyframes, sum(self.sent_bytes.values())
        out["descriptor_bytes_per_keyframe"] = self.sent_bytes["keyframes"] / kf if kf else 0.0
        out["bytes_per_keyframe"] = total / kf if kf else 0.0
        loops = self.loops_confirmed
        out["request_bytes_per_confirmed_loop"] = (
            self.sent_bytes["request"] / loops if loops else 0.0
        )
        return out


class FleetExchange:
    """One robot's fleet exchange around its pipeline (see the module docstring)."""

    def __init__(
        self,
        pipeline: LoopClosurePipeline,
        config: FleetConfig,
        send: Callable[[Outgoing], int | None],
        clock: Callable[[], float] = time.monotonic,
        first_request_id: int | None = None,
    ) -> None:
        self.pipe, self.config, self.send, self.clock = pipeline, config, send, clock
        self.tag = model_tag(pipeline.model.fingerprint)
        self.store = peer_store(config, pipeline.model.config.desc_dim, self.tag,
                                lambda: self.pipe.place_map)  # fmt: skip
        self.budget = RequestBudget(config.budget, config.period_s, config.select)
        self.counts = FleetCounts()
        self._next_id = secrets.randbits(31) if first_request_id is None else first_request_id
        self._pending: OrderedDict[int, float] = OrderedDict()  # request id -> sent at
        self._closed: OrderedDict[int, str] = OrderedDict()  # id -> "answered" / "timed out"
        self._scored: OrderedDict[tuple[str, str, int], None] = OrderedDict()  # as owner
        self._published: dict[int, float] = {}  # own keyframe id -> stamp, as published

    # ---- own keyframes -------------------------------------------------------------------
    def on_keyframe(self, outcome: FrameOutcome) -> int:
        """Publish the descriptor of a new own keyframe and request scores for peer candidates
        that pass the global floor (within the budget); -> requests sent now."""
        kf_id = outcome.keyframe_id
        if kf_id is None:
            return 0
        c = self.config
        desc = self.pipe.place_map.get_desc([kf_id])[0]
        if c.peer_search == "broadcast":  # "milvus": the peers find its row in the collection
            msg = KeyframeDescriptor(c.robot, c.session, self.tag, kf_id, outcome.stamp, desc)
            self._send("keyframes", "", msg)
        self._published[kf_id] = outcome.stamp
        self.counts.keyframes += 1
        hits = self.store.search(desc, c.top_k, self.pipe.config.global_floor)
        proposals = [Proposal(found[0].similarity, kf_id, outcome.stamp, owner, found)
                     for owner, found in hits.items()]  # fmt: skip
        return self._propose(proposals)

    def tick(self) -> int:
        """Time passes (the node calls this every second): count timed-out requests, and send
        what a period that ended selected; -> requests sent."""
        return self._propose([])

    def flush(self) -> int:
        """Send what the current period selected so far (end of an offline run)."""
        self.expire()
        send, cut = self.budget.flush()
        self.counts.budget_cut += cut
        return sum(self._ask(p) for p in send)

    def _propose(self, proposals: list[Proposal]) -> int:
        self.expire()
        send, cut = self.budget.offer(self.clock(), proposals)
        self.counts.budget_cut += cut
        return sum(self._ask(p) for p in send)

    def _ask(self, p: Proposal) -> int:
        """Send one score request with the query's dense tokens (and features); -> 1, or 0
        when the query keyframe left the map meanwhile (cleared, or another map loaded)."""
        pm, c = self.pipe.place_map, self.config
        if p.query_id >= len(pm) or pm.meta(p.query_id).stamp != p.query_stamp:
            self.counts.query_gone += 1
            return 0
        (robot, session), found = p.owner, p.hits
        features = pm.features(p.query_id) if c.send_features else b""
        req = ScoreRequest(c.robot, c.session, self.tag, self._next_id, robot, session,
                           p.query_id, p.query_stamp, [h.keyframe_id for h in found],
                           [h.similarity for h in found], pm.get_dense([p.query_id])[0],
                           features)  # fmt: skip
        try:
            self._send("request", robot, req)
        except FleetMessageError as err:  # the transport cannot reach that owner: counted
            self.counts.skipped[err.reason] += 1
            return 0
        self._pending[self._next_id] = self.clock()
        self._next_id = (self._next_id + 1) % (1 << 32)
        return 1

    def expire(self) -> int:
        """Count requests unanswered for timeout_s as lost (an owner that left); -> how many."""
        now, gone = self.clock(), []
        for rid, sent_at in self._pending.items():
            if now - sent_at >= self.config.timeout_s or now < sent_at:
                gone.append(rid)
        for rid in gone:
            del self._pending[rid]
            self._remember(self._closed, rid, "timed out")
        self.counts.timeouts += len(gone)
        return len(gone)

    @property
    def pending(self) -> int:
        return len(self._pending)

    # ---- messages from other robots ------------------------------------------------------
    def receive(self, channel: str, data: bytes) -> InterRobotLoop | None:
        """Handle the codec bytes of one message of `channel`; -> the inter-robot loop decided
        when it was a score request (accepted or not), else None. Never raises on bad input:
        counts it."""
        self._count_received(channel, len(data))
        try:
            return self._dispatch(channel, decode(data))
        except FleetMessageError as err:
            self.counts.skipped[err.reason] += 1
        return None

    def handle(self, channel: str, msg: Message, size: int) -> InterRobotLoop | None:
        """As `receive`, for a message that arrived decoded (a typed ROS message converted by
        `fleet.typed`) and took `size` bytes on the wire."""
        self._count_received(channel, size)
        try:
            return self._dispatch(channel, check(msg))
        except FleetMessageError as err:
            self.counts.skipped[err.reason] += 1
        return None

    def reject(self, channel: str, size: int, reason: str) -> None:
        """Count a message the transport could not even convert (a typed message that cannot
        be a fleet message)."""
        self._count_received(channel, size)
        self.counts.skipped[reason] += 1

    def _count_received(self, channel: str, size: int) -> None:
        self.counts.received[channel] += 1
        self.counts.received_bytes[channel] += size

    def _dispatch(self, channel: str, msg: Message) -> InterRobotLoop | None:
        if not isinstance(msg, CHANNELS.get(channel, ())):
            raise FleetMessageError("wrong channel", f"{type(msg).__name__} on {channel}")
        if msg.model != self.tag:
            raise FleetMessageError("wrong model", f"from robot {msg.robot!r}")
        if isinstance(msg, KeyframeDescriptor):
            self._descriptor(msg)
        elif isinstance(msg, ScoreRequest):
            return self._request(msg)
        else:
            self._response(msg)
        return None

    def _descriptor(self, msg: KeyframeDescriptor) -> None:
        own = (msg.robot, msg.session) == (self.config.robot, self.config.session)
        if own and msg.keyframe_id in self._published:
            self.counts.ignored += 1  # our own, heard back on the shared topic
            return
        self.store.add(msg)

    def _request(self, req: ScoreRequest) -> InterRobotLoop | None:
        if req.robot == self.config.robot:
            raise FleetMessageError("own robot", f"a request from {req.robot!r}")
        key = (req.robot, req.session, req.request_id)
        if key in self._scored:
            raise FleetMessageError("duplicate", f"request {req.request_id} of {req.robot!r}")
        session = self.config.session  # "milvus": any keyframe of the map, of its own session
        if self.config.peer_search == "milvus":
            check_own_keyframes(self.pipe, req, self.config.robot)
            session = req.owner_session
        else:
            self._check_published(req.candidate_ids)
        try:
            loop, response = score_request(self.pipe, req, self.config.robot, session)
        except FleetMessageError:
            raise
        except (PairVPRError, ValueError, RuntimeError) as err:
            raise FleetMessageError("scoring failed", str(err)) from err
        self._remember(self._scored, key, None)
        self._send("response", "", response)
        if loop.record.accepted:
            self.counts.loops_accepted += 1
        else:
            self.counts.loops_rejected += 1
        return loop

    def _check_published(self, ids: list[int]) -> None:
        """Only keyframes this robot published, still the same ones (a map cleared or loaded
        since gives the ids to other keyframes: "stale keyframe")."""
        pm = self.pipe.place_map
        for kf_id in ids:
            if kf_id not in self._published:
                raise FleetMessageError("unknown keyframe", f"id {kf_id} was never published")
            if kf_id >= len(pm) or pm.meta(kf_id).stamp != self._published[kf_id]:
                raise FleetMessageError("stale keyframe", f"id {kf_id} is another keyframe now")

    def _response(self, msg: ScoreResponse) -> None:
        if msg.requester_robot != self.config.robot:
            self.counts.ignored += 1  # on the shared response topic, for another robot
            return
        if msg.requester_session != self.config.session:
            raise FleetMessageError("stale session", f"response for {msg.requester_session!r}")
        if self._pending.pop(msg.request_id, None) is None:
            state = self._closed.get(msg.request_id)
            reason = {"answered": "duplicate", "timed out": "late"}.get(state, "unknown request")
            raise FleetMessageError(reason, f"response to request {msg.request_id}")
        self._remember(self._closed, msg.request_id, "answered")
        self.counts.loops_confirmed += int(msg.accepted)

    # ---- helpers ---------------------------------------------------------------------------
    def _send(self, channel: str, target: str, msg: Message) -> None:
        """Hand `msg` to the transport; its bytes are counted as the transport reports them
        (a typed ROS message: its serialized size), else as the codec's."""
        data = encode_message(msg)
        size = self.send(Outgoing(channel, target, data, msg))
        self.counts.sent[channel] += 1
        self.counts.sent_bytes[channel] += len(data) if size is None else size

    @staticmethod
    def _remember(memory: OrderedDict, key, value) -> None:
        memory[key] = value
        while len(memory) > REMEMBERED:
            memory.popitem(last=False)

    def summary(self) -> dict:
        """Counts, bytes and the peer store (keyframes per robot/session, estimated missing)."""
        out = self.counts.summary()
        out.update(peer_keyframes=self.store.owners(), peer_missing=self.store.missing(),
                   peer_reordered=self.store.reordered, pending=self.pending,
                   peer_searches_skipped=self.store.skipped)  # fmt: skip
        return out
