"""What a loop closure becomes for back ends, ROS-free: the between-factor (`factor`: LoopFactor
and its nav_msgs/Odometry encoding) and the content of every loop-closure topic (`loop`: the
LIO-SAM pair, detail, JSON, typed). Types are passed in (rclpy classes or a rosbags typestore).
"""

from pair_vpr_ros.messages.factor import (
    LoopFactor,
    factor_from_msg,
    factor_from_record,
    factor_msg,
)
from pair_vpr_ros.messages.loop import LoopMessages, loop_messages, record_dict, typed_msg

__all__ = [
    "LoopFactor",
    "LoopMessages",
    "factor_from_msg",
    "factor_from_record",
    "factor_msg",
    "loop_messages",
    "record_dict",
    "typed_msg",
]
