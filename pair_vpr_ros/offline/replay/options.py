"""What a replay is told (`ReplayOptions`) and what it reports (`ReplaySummary`, written as
``summary.json``); the library function is ``offline.replay.replay_bag``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.model.threads import check_threads
from pair_vpr_ros.place_map import IndexConfig

if TYPE_CHECKING:
    from pair_vpr_ros.offline.report.loop_truth import LoopEvaluation


@dataclass(frozen=True)
class ReplayOptions:
    """What a replay reads and writes (the detector's settings are a ``DetectorConfig``).

    Topics: None picks by the bag's contents (the only image / depth / camera_info topic; pose
    and ground-truth topics as ``pose_topics.choose_pose_topics`` says), ``"none"`` uses none.
    ``pose_topic`` poses are attached to keyframes (and saved in the map); ``gt_topic`` is the
    evaluation's ground truth. Depth is matched to images within ``depth_tolerance`` s, poses
    within ``pose_tolerance`` s. ``map_dir`` defaults to ``OUT/map``; a saved map (or a folder
    of other files) there is refused unless ``overwrite``.
    """

    topic: str | None = None
    topics: tuple[str, ...] = ()  # several: a rig, one camera per topic (offline/bags/rig.py)
    rig_file: str | Path | None = None  # a rig file (loops/rig.py parse_rig): several cameras
    pose_topic: str | None = None
    gt_topic: str | None = None
    depth_topic: str | None = None
    camera_info_topic: str | None = None
    right_topic: str | None = None  # stereo: rectified right image (offline/bags/stereo.py)
    right_camera_info_topic: str | None = None
    gt_radius: float = 10.0  # m: a loop is true when its keyframes lie this close
    pose_tolerance: float = 0.2
    depth_tolerance: float = 0.02
    batch_size: int = 8
    max_frames: int | None = None
    max_image_pixels: int = MAX_PIXELS
    device: str = "cpu"
    precision: str = "fp32"  # and backend: as the node's parameters
    backend: str = "torch"
    openvino_cache_dir: str = "auto"  # '' = no cache
    openvino_calibration: str = ""  # int8 calibration bag / image folder; '' = synthetic scenes
    openvino_calibration_topic: str = ""  # '' = the calibration bag's only image topic
    num_threads: int = 0  # CPU threads of the process (model/threads.py); 0 = auto
    write_bag: bool = False
    map_dir: str | Path | None = None
    save_map: bool = True
    overwrite: bool = False
    progress: bool = True
    robot_id: str = ""  # '' = "robot" (identity.py; a replay has no namespace)
    session_id: str = ""  # '' = the start time, UTC
    prior_maps: tuple[str | Path, ...] = ()  # read-only maps searched with the live one
    # Called with each choice of topic as soon as it is made, before the model loads (the
    # command line prints them as the run's first lines); they are in summary.notes either way.
    announce: Callable[[str], None] | None = None
    index: str | IndexConfig = "flat"  # the map's index (kind "milvus": docs/milvus.md)
    report: bool = True  # OUT/report/: the pages that show every decision (offline.report.html)
    target_precision: float = 0.99  # of OUT/suggested_params.yaml (with ground truth)
    # the node parameters the run was set up from (a --params-file's), for suggested_params.yaml
    params_values: Mapping[str, Any] | None = None

    def check(self) -> None:
        """ConfigError naming the first value out of range."""
        check_threads(self.num_threads)
        if not (math.isfinite(self.gt_radius) and self.gt_radius > 0):
            raise ConfigError(
                f"gt_radius must be a finite number of metres > 0, got {self.gt_radius}"
            )
        if not (math.isfinite(self.target_precision) and 0 < self.target_precision <= 1):
            raise ConfigError(f"target_precision must be in (0, 1], got {self.target_precision}")

    def map_path(self, out: Path) -> Path:
        return Path(self.map_dir) if self.map_dir else out / "map"


@dataclass
class ReplaySummary:
    """What one replay did; ``error`` says where it stopped when it did not finish."""

    bag: str
    topic: str
    pose_topic: str | None  # attached to keyframes (saved in the map)
    gt_topic: str | None = None  # ground truth of ``evaluation``
    depth_topic: str | None = None
    camera_info_topic: str | None = None
    frames: int = 0  # image messages read
    skipped: int = 0  # messages that did not deserialise or convert
    skip_reasons: dict[str, int] = field(default_factory=dict)  # up to 10 distinct reasons
    bad_poses: int = 0  # pose messages with NaN / inf values, skipped
    stamps_backwards: int = 0  # usable images stamped earlier than the one before
    stamps_repeated: int = 0  # ... stamped the same as the one before
    geometry_skips: dict[str, int] = field(default_factory=dict)  # depth / camera_info problems
    keyframes: int = 0
    candidates: int = 0  # loop records (best candidate per queried keyframe)
    pipeline_counts: dict[str, int] = field(default_factory=dict)  # rate_limited, encoded, ...
    loops: int = 0  # accepted loop closures
    seconds: float = 0.0
    fps: float = 0.0
    out_dir: str = ""
    map_dir: str | None = None
    bag_out: str | None = None
    evaluation: dict[str, Any] | None = None  # the run's own loops (live map)
    prior_evaluation: dict[str, Any] | None = None  # loops into prior maps (report.prior_truth)
    config: dict[str, Any] = field(default_factory=dict)  # the DetectorConfig used
    model: str = ""  # the model's fingerprint (weights, input size, descriptor size)
    threads: int = 0  # the CPU threads the process ran on (model/threads.py); 0: not set
    robot: str = ""  # the query side of every loop: this replay's robot and session
    session: str = ""
    prior_maps: list[dict[str, Any]] = field(default_factory=list)  # dir, keyframes, sessions
    loops_by_match: dict[str, int] = field(default_factory=dict)  # "robot/session" -> loops
    rig: dict[str, Any] | None = None  # several cameras: each one's topic and frames, rig counts
    # recall of revisits driven the same way and the other way (report.directions)
    directions: dict[str, Any] | None = None
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # how each topic was picked
    error: str | None = None
    interrupted: bool = False  # stopped by Ctrl-C (``error`` says after how many messages)
    report: dict[str, Any] | None = None  # OUT/report/: folder, size, seconds spent writing it
    suggestion: dict[str, Any] | None = None  # OUT/suggested_params.yaml: threshold, figures
    # the evaluation itself, whole PR curves included (library callers; not in summary.json,
    # which keeps ``evaluation``'s figures)
    loop_evaluation: LoopEvaluation | None = field(default=None, repr=False, compare=False)

    def line(self) -> str:
        live = self.loops_by_match.get(f"{self.robot}/{self.session}", 0)
        split = f" ({live} live, {self.loops - live} into prior maps)" if self.prior_maps else ""
        return (
            f"frames {self.frames}, keyframes {self.keyframes}, loops {self.loops}{split}, "
            f"skipped {self.skipped}, {self.seconds:.1f} s, {self.fps:.1f} frames/s"
        )

    def to_dict(self) -> dict[str, Any]:
        out = asdict(replace(self, loop_evaluation=None))
        del out["loop_evaluation"]
        return out
