"""`LocalBus`: fleet exchanges of several robots in one process (offline runs, tests), with the
faults of a real network on demand: lost, duplicated, reordered and damaged messages, and
robots that leave and come back.

Like the ROS topics: descriptors and responses reach every robot (the sender hears its own),
a score request only its owner. Delivery is synchronous: `deliver()` empties the queue,
including the responses that the requests it delivers produce.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.fleet.exchange import FleetExchange, Outgoing
from pair_vpr_ros.fleet.owner import InterRobotLoop


@dataclass(frozen=True)
class Faults:
    """Per-delivery chances: drop (lost), duplicate (delivered twice), reorder (held back until
    the next message of the same channel to the same robot has passed), corrupt (one byte
    changed)."""

    drop: float = 0.0
    duplicate: float = 0.0
    reorder: float = 0.0
    corrupt: float = 0.0
    seed: int = 0


class LocalBus:
    def __init__(self, faults: Faults | None = None) -> None:
        self.faults = faults or Faults()
        self._rng = np.random.default_rng(self.faults.seed)
        self.exchanges: dict[str, FleetExchange] = {}
        self.away: set[str] = set()  # robots off the network: nothing to or from them
        self._queue: deque[tuple[str, Outgoing]] = deque()
        self._held: list[tuple[FleetExchange, Outgoing]] = []
        self.loops: list[InterRobotLoop] = []  # every inter-robot loop decided, in order
        self.dropped = 0

    def sender(self, robot: str) -> Callable[[Outgoing], None]:
        """The `send` callback of robot `robot`'s exchange."""
        return lambda out: self._queue.append((robot, out))

    def join(self, exchange: FleetExchange) -> None:
        self.exchanges[exchange.config.robot] = exchange
        self.away.discard(exchange.config.robot)

    def leave(self, robot: str) -> None:
        self.away.add(robot)

    def deliver(self, flush: bool = False) -> list[InterRobotLoop]:
        """Deliver everything queued (and what that produces); -> the loops decided. Messages
        held back for reordering wait for a later message to overtake them (a later call), or
        for `flush`."""
        start = len(self.loops)
        while self._queue or (flush and self._held):
            if not self._queue:  # nothing left to overtake the held messages
                held, self._held = self._held, []
                for exchange, out in held:
                    self._receive(exchange, out)
                continue
            robot, out = self._queue.popleft()
            if robot in self.away:
                self.dropped += 1
                continue
            for name, exchange in list(self.exchanges.items()):
                if (out.target and name != out.target) or name in self.away:
                    continue
                self._with_faults(exchange, out)
        return self.loops[start:]

    def _with_faults(self, exchange: FleetExchange, out: Outgoing) -> None:
        f, rng = self.faults, self._rng
        if rng.random() < f.drop:
            self.dropped += 1
            return
        if rng.random() < f.corrupt:
            data = bytearray(out.data)
            data[int(rng.integers(len(data)))] ^= 0xFF
            out = Outgoing(out.channel, out.target, bytes(data))
        copies = 2 if rng.random() < f.duplicate else 1
        if rng.random() < f.reorder:
            self._held += [(exchange, out)] * copies
            return
        for _ in range(copies):
            self._receive(exchange, out)
        # held messages of this channel to this robot: overtaken now, delivered late
        overtaken = [h[0] is exchange and h[1].channel == out.channel for h in self._held]
        late = [h for h, o in zip(self._held, overtaken, strict=True) if o]
        self._held = [h for h, o in zip(self._held, overtaken, strict=True) if not o]
        for other, msg in late:
            self._receive(other, msg)

    def _receive(self, exchange: FleetExchange, out: Outgoing) -> None:
        loop = exchange.receive(out.channel, out.data)
        if loop is not None:
            self.loops.append(loop)
