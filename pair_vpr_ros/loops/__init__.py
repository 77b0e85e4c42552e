"""The loop-closure pipeline, ROS-free: frames in, loop records out.

`pipeline.LoopClosurePipeline` is the one object the node, the replay and the map builder drive;
`frames` holds its inputs and outputs, `detector` the keyframe and acceptance rules, `records`
the `Candidate` and the `LoopRecord`, `map_search` the top-K over the live and prior maps,
`scoring` the pair scores, `recency` the recent-keyframe exclusion, `pipeline_maps` the map's life
cycle (and a match's data from its own map) and `prior_maps` the saved maps opened read-only.
"""

from pair_vpr_ros.loops.detector import DetectorConfig, preset
from pair_vpr_ros.loops.frames import Frame, FrameOutcome, PipelineCounts
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.prior_maps import open_prior_maps
from pair_vpr_ros.loops.records import LoopRecord, rerank_score

__all__ = [
    "DetectorConfig",
    "Frame",
    "FrameOutcome",
    "LoopClosurePipeline",
    "LoopRecord",
    "PipelineCounts",
    "open_prior_maps",
    "preset",
    "rerank_score",
]
