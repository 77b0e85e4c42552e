"""What a loop closure becomes for back ends, ROS-free: the between-factor (`factor`: LoopFactor
and its nav_msgs/Odometry encoding), the content of every loop-closure topic (`loop`: the
LIO-SAM pair, detail, JSON, typed) and the loop image a person looks at (`loop_image`: query |
match with the inlier matches). Types are passed in (rclpy classes or a rosbags typestore).
"""

from pair_vpr_ros.messages.factor import (
    LoopFactor,
    factor_from_msg,
    factor_from_record,
    factor_msg,
)
from pair_vpr_ros.messages.loop import LoopMessages, loop_messages, record_dict, typed_msg
from pair_vpr_ros.messages.loop_image import LoopPictures, draw_loop

__all__ = [
    "LoopFactor",
    "LoopMessages",
    "LoopPictures",
    "draw_loop",
    "factor_from_msg",
    "factor_from_record",
    "factor_msg",
    "loop_messages",
    "record_dict",
    "typed_msg",
]
