"""Pair-VPR loop-closure detection: ROS-free core plus a thin ROS 2 node.

Pipeline: model -> place_map -> detector -> pipeline -> {node, replay, evaluate, train}.
"""

__version__ = "0.1.0"
