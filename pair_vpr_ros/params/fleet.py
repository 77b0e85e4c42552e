"""vpr_node's fleet parameters, all start-up only: rows (name, default, description[, low,
high][, {keyword: value}]) that `params.PARAMS` turns into `ParamSpec`s (this module must not
import `params`, which imports it), kept here so the fleet's settings sit with the fleet;
`fleet_config` turns a parameter set into a `FleetConfig`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pair_vpr_ros.fleet.exchange import FleetConfig

FLEET_PARAMS: tuple[tuple, ...] = (
    ("fleet_enable", False, "share keyframe descriptors with other robots and score their "
       "requests (inter-robot loops, docs/fleet-exchange.md); off: nothing is sent or heard"),
    ("fleet_keyframes_topic", "/fleet/keyframes", "shared topic of every robot's keyframe "
       "descriptors (~1.1 KB each)"),
    ("fleet_request_topic", "/fleet/score_request", "score requests to robot R go to "
       "<this>/R (R: the owner's robot id); each carries one query's dense tokens"),
    ("fleet_response_topic", "/fleet/score_response", "shared topic of the owners' answers"),
    ("fleet_budget", 4, "score requests sent per fleet_period at most (0: descriptors only)",
       0, 1000),
    ("fleet_period", 10.0, "seconds of the request budget's period", 0.1, 3600.0),
    ("fleet_select", "best", "which candidates the budget lets through: best (a period's most "
       "similar, sent when the period ends) or first (sent at once while the budget lasts)",
       {"choices": ("best", "first")}),
    ("fleet_peer_search", "broadcast", "how other robots' keyframes are found: broadcast "
       "(publish each keyframe's descriptor, search those heard) or milvus (search the other "
       "robots' rows of the Milvus collection every robot's map shares: index milvus, one "
       "milvus_uri and milvus_collection; nothing is broadcast)",
       {"choices": ("broadcast", "milvus")}),
    ("fleet_top_k", 3, "peer keyframes searched per own keyframe (those at or above "
       "global_floor are sent to their owner for scoring)", 1, 64),
    ("fleet_timeout", 10.0, "a request unanswered this many seconds is counted lost",
       0.1, 3600.0),
    ("fleet_peers", "", "robot ids listened to, comma-separated ('' = any robot)"),
    ("fleet_messages", "auto", "message types on the fleet topics: typed (pair_vpr_ros_interfaces"
       "/KeyframeDescriptor, ScoreRequest, ScoreResponse), bytes (the fleet codec in "
       "std_msgs/UInt8MultiArray) or auto (typed when that package is installed); every robot "
       "of a fleet must use the same", {"choices": ("auto", "typed", "bytes")}),
    ("fleet_send_features", True, "send the query's keypoints with a request, so the owner "
       "can compute the loop's relative pose (~140 KB with 1000 SIFT keypoints)"),
)  # fmt: skip


def fleet_config(values: Mapping[str, Any], robot: str, session: str) -> FleetConfig:
    """The `FleetConfig` of a full parameter set (ConfigError when it is not valid)."""
    peers = tuple(p.strip() for p in values["fleet_peers"].split(",") if p.strip())
    return FleetConfig(
        robot=robot,
        session=session,
        budget=values["fleet_budget"],
        period_s=values["fleet_period"],
        top_k=values["fleet_top_k"],
        timeout_s=values["fleet_timeout"],
        peers=peers,
        send_features=values["fleet_send_features"],
        select=values["fleet_select"],
        peer_search=values["fleet_peer_search"],
    )
