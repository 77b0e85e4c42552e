"""Other robots' keyframes in the shared collection (the fleet's `fleet_peer_search: milvus`).

Several robots' maps write one collection, each under its own writer key, and every row says
whose keyframe it is: `robot` and `session` fields, and the keyframe's id in the owner's map in
the low 32 bits of `pk` (expr.py). A robot therefore finds other robots' candidates with one
filtered search of that collection instead of keeping their broadcast descriptors; the owner
still scores them with its own dense tokens (fleet/owner.py). Rows a search finds that the
owner no longer has (a run never saved, a crash) cost one refused request at most: the owner
checks every id against its own map and session, and scores only its own keyframes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pair_vpr_ros.errors import MapUnavailableError
from pair_vpr_ros.place_map.milvus import client as mc
from pair_vpr_ros.place_map.milvus.collection import search_params
from pair_vpr_ros.place_map.milvus.expr import ID_BITS, quote
from pair_vpr_ros.place_map.milvus.index import MAX_LIMIT, MilvusIndex, _faults


@dataclass(frozen=True)
class PeerRow:
    """One other robot's keyframe found in the shared collection."""

    robot: str
    session: str
    keyframe_id: int  # in the owner's map
    stamp: float
    similarity: float


def peer_expr(robot: str, peers: tuple[str, ...] = ()) -> str:
    """Rows of robots other than `robot` (of `peers` only, when given)."""
    expr = f"robot != {quote(robot)}"
    if peers:
        expr += " and robot in [" + ", ".join(quote(p) for p in peers) + "]"
    return expr


def search_peers(
    index: MilvusIndex, desc: np.ndarray, k: int, robot: str, peers: tuple[str, ...] = ()
) -> list[PeerRow]:
    """desc [dim] -> the `k` most similar keyframes of other robots in `index`'s collection,
    best first. MapUnavailableError when Milvus does not answer (the caller counts a skip).
    At `Bounded` consistency other writers' newest rows show up within the server's
    `common.gracefulTime` (5 s by default)."""
    query = np.asarray(desc, np.float32).reshape(1, index.dim)
    try:
        found = index.client.search(
            index.collection, query, filter=peer_expr(robot, peers),
            limit=min(int(k), MAX_LIMIT), anns_field="desc",
            search_params=search_params(index.config, k, index.index_type),
            output_fields=["robot", "session", "stamp"],
            consistency_level=index.config.milvus_consistency,
        )[0]  # fmt: skip
    except _faults() as err:
        raise MapUnavailableError(
            f"collection {index.collection!r} in {mc.where(index.uri)} did not answer a peer "
            f"search ({mc._reason(err)}): skipped"
        ) from err
    mask = (1 << ID_BITS) - 1
    return [
        PeerRow(
            str(h["entity"]["robot"]),
            str(h["entity"]["session"]),
            int(h.id) & mask,
            float(h["entity"]["stamp"]),
            float(h["distance"]),
        )  # fmt: skip
        for h in found
    ]
