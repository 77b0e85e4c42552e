"""Fleet exchange (issue 22 part 4): robots share compact keyframe descriptors, search each
other's in their own process, and ask the owner of a candidate to pair-score it with its dense
tokens. ROS-free; the node (`ros/fleet.py`) and the offline runner (`offline/fleet/replay.py`)
carry the bytes. See docs/fleet-exchange.md."""

from pair_vpr_ros.fleet.exchange import FleetConfig, FleetCounts, FleetExchange, Outgoing
from pair_vpr_ros.fleet.local import Faults, LocalBus
from pair_vpr_ros.fleet.messages import (
    KeyframeDescriptor,
    ScoreRequest,
    ScoreResponse,
    decode,
    encode,
)
from pair_vpr_ros.fleet.owner import InterRobotLoop
from pair_vpr_ros.fleet.wire import model_tag

__all__ = [
    "Faults",
    "FleetConfig",
    "FleetCounts",
    "FleetExchange",
    "InterRobotLoop",
    "KeyframeDescriptor",
    "LocalBus",
    "Outgoing",
    "ScoreRequest",
    "ScoreResponse",
    "decode",
    "encode",
    "model_tag",
]
