"""The table of `vpr_node`'s parameters (`PARAMS`), ROS-free, and its row type `ParamSpec`.

The package (`from pair_vpr_ros import params`) exports its public names; checks live in
`check`, parameter files in `file`, the configs built from the values in `configs`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pair_vpr_ros.identity import DEFAULT_ROBOT, RULE
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.params.fleet import FLEET_PARAMS
from pair_vpr_ros.place_map.dense_codec import DEFAULT_CODEC

# A tuple default: a fixed-size double array, or (ParamSpec.strings) a string array of any size.
Value = bool | int | float | str | tuple[float, ...] | tuple[str, ...]
RANDOM_TINY = "random-tiny"  # test-only weights value: a tiny random network (finds nothing real)


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: its default fixes the ROS type; `low`/`high` bound numbers."""

    name: str
    default: Value
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = False
    strings: bool = False  # a string array (default ()): ROS STRING_ARRAY


def _p(name: str, default: Value, description: str, *bounds: float, **kw: Any) -> ParamSpec:
    low, high = bounds if bounds else (None, None)
    return ParamSpec(name, default, description, low, high, **kw)


RO = dict(read_only=True)
PARAMS: tuple[ParamSpec, ...] = (
    # ---- model (start-up only)
    _p("weights", "", "Pair-VPR checkpoint (.pth), e.g. /path/pairvpr-vitB.pth; '' = "
       "$PAIRVPR_WEIGHTS, else the one .pth in $XDG_DATA_HOME/pair_vpr_ros/ (default "
       f"~/.local/share/pair_vpr_ros/); '{RANDOM_TINY}' builds a tiny random network (tests only)",
       **RO),
    _p("device", "cpu", "torch device: cpu, cuda, cuda:1, auto (cuda when there is one)", **RO),
    _p("precision", "fp32", "fp32; int8 (dynamic quantization, CPU only); bf16 (autocast, CPU "
       "or GPU); fp16 (autocast, GPU only)", choices=("fp32", "int8", "bf16", "fp16"), **RO),
    _p("backend", "torch", "inference runtime: torch (the reference); openvino (CPU only, "
       "optional package: pip install 'pair_vpr_ros[openvino]'; precision fp32, bf16 or int8 "
       "= static int8 calibrated at the first start, see openvino_cache_dir)",
       choices=("torch", "openvino"), **RO),
    _p("openvino_cache_dir", "auto", "backend openvino: folder that keeps the converted (int8: "
       "quantized) model, so later starts skip export and calibration; auto = "
       "$XDG_CACHE_HOME/pair_vpr_ros/openvino (default ~/.cache/pair_vpr_ros/openvino); '' = no "
       "cache", **RO),
    _p("openvino_calibration", "", "backend openvino, precision int8: calibrate on images picked "
       "evenly from this rosbag (folder, .mcap, .db3, .bag) or image folder (sorted by "
       "name) of the robot's own camera; '' = synthetic scenes (docs/performance.md)", **RO),
    _p("openvino_calibration_topic", "", "image topic of an openvino_calibration bag ('' = its "
       "only one)", **RO),
    _p("image_size", 0, "network input side in pixels, a multiple of 14; 0: the checkpoint's",
       0, 1022, **RO),
    _p("num_threads", 0, "CPU threads of the network and the libraries beside it (torch, "
       "OpenMP / BLAS, OpenCV, OpenVINO); 0 = auto: 1 for a light network such as the demo "
       "model, every usable core for ViT-B and larger (docs/performance.md, sharing the CPU)",
       0, 1024, **RO),
    _p("index", "flat", "map index: flat (exact), ivf (exact below 25,000 keyframes, then k-means "
       "lists: large maps), hnsw (graph) or milvus (a Milvus collection: milvus_uri; optional "
       "package: pip install 'pair_vpr_ros[milvus]')",
       choices=("flat", "hnsw", "ivf", "milvus"), **RO),
    _p("dense_codec", DEFAULT_CODEC, "how a new map stores each keyframe's dense tokens: p4 "
       "(200 KiB per ViT-B keyframe: a basis per map fitted on its first 16 keyframes for the "
       "pair decoder's input layer, 1.2 MB once; decodes 4-10x slower than q4), q4 (4 bits and "
       "a float16 scale per channel, the same size: faster, less faithful re-ranking), q4a (4 "
       "bits on each channel's own range, the same size: lower error, no better re-ranking "
       "agreement) or f16 (uncompressed float16, 794 KiB); a loaded map keeps its own "
       "(docs/performance.md, compact keyframes)", choices=("p4", "q4", "q4a", "f16"), **RO),
    _p("milvus_uri", "", "index milvus: a milvus-lite file (path ending in .db, created if "
       "missing) or a Milvus server address (http://host:19530)", **RO),
    _p("milvus_collection", "pairvpr_keyframes", "index milvus: the collection (maps of one "
       "model may share it, see docs/milvus.md)", **RO),
    _p("milvus_index", "IVF_FLAT", "index milvus: the collection's vector index (made when the "
       "collection is created; docs/milvus.md compares them)",
       choices=("IVF_FLAT", "HNSW", "FLAT"), **RO),
    _p("milvus_token_env", "PAIRVPR_MILVUS_TOKEN", "index milvus: name of the environment "
       "variable that holds the server token (the token is never a parameter, never logged)",
       **RO),
    _p("milvus_consistency", "Bounded", "index milvus: Bounded (no wait; the node also searches "
       "its keyframes of the last 10 s, so each is found at once), Session or Strong (the "
       "server waits for its time tick, ~200 ms a search; docs/milvus.md)",
       choices=("Bounded", "Session", "Strong"), **RO),
    # ---- inputs (start-up only)
    _p("image_topic", "image", "sensor_msgs/Image input topic ('' = none)", **RO),
    _p("compressed_image_topic", "", "sensor_msgs/CompressedImage input topic ('' = none)", **RO),
    _p("pose_topic", "", "pose input topic attached to keyframes ('' = none)", **RO),
    _p("pose_type", "odometry", "message type of pose_topic",
       choices=("odometry", "pose_stamped", "pose_with_covariance_stamped"), **RO),
    _p("pose_buffer_size", 2000, "poses kept for matching frames by stamp", 10, 1000000, **RO),
    _p("depth_topic", "", "sensor_msgs/Image depth aligned with the colour image (16UC1 mm or "
       "32FC1 m) for metric relative poses ('' = none: monocular)", **RO),
    _p("camera_info_topic", "", "sensor_msgs/CameraInfo of the colour camera: intrinsics for "
       "relative poses ('' = none: use the camera_* parameters)", **RO),
    _p("depth_tolerance", 0.02, "largest stamp gap (s) between an image and its depth image",
       0.0, 1.0, **RO),
    _p("depth_max_delay", 0.2, "how long (s, wall clock) a frame waits for its depth image to "
       "arrive (drivers often publish depth after colour); a later one is not used, counted as "
       "depth_late in /diagnostics", 0.0, 10.0, **RO),
    _p("camera_fx", 0.0, "fallback intrinsics when no camera_info arrives: focal length x in "
       "pixels of the incoming images (0 = none: no relative poses without camera_info)",
       0.0, 1.0e6, **RO),
    _p("camera_fy", 0.0, "fallback focal length y, px (0 = camera_fx)", 0.0, 1.0e6, **RO),
    _p("camera_cx", -1.0, "fallback principal point x, px (-1 = image centre)", -1.0, 1.0e6,
       **RO),
    _p("camera_cy", -1.0, "fallback principal point y, px (-1 = image centre)", -1.0, 1.0e6,
       **RO),
    _p("camera_distortion_model", "none", "fallback distortion model",
       choices=("none", "plumb_bob", "rational_polynomial", "equidistant"), **RO),
    _p("camera_distortion", "", "fallback distortion coefficients, comma-separated (plumb_bob: "
       "k1, k2, t1, t2, k3; equidistant: k1, k2, k3, k4)", **RO),
    _p("relative_pose", True, "compute T_match_query (+ covariance) for accepted loops: "
       "features of every keyframe are extracted and stored in the map", **RO),
    _p("features", "sift", "keypoints for relative poses: sift (accurate) or orb (cheaper)",
       choices=("sift", "orb"), **RO),
    _p("max_features", 1000, "keypoints per keyframe at most", 50, 100000, **RO),
    _p("feature_storage", "compact", "how the map stores each keyframe's features: compact "
       "(the 500 strongest SIFT keypoints, 4-bit descriptors, float16 depth: 36 KB) or full "
       "(every keypoint as extracted: 140 KB for 1000 SIFT)", choices=("compact", "full"), **RO),
    _p("depth_sigma_a", 0.0012, "depth noise sigma_z = a + b z^2 (m): a; defaults from "
       "published Kinect noise studies (docs/real-cameras.md)", 0.0, 10.0, **RO),
    _p("depth_sigma_b", 0.0019, "depth noise: b (1/m); depth from the stereo pair "
       "(right_image_topic) has its own sigma per pixel from the matching instead",
       1e-9, 10.0, **RO),
    _p("max_depth", 0.0, "depth beyond this (m) is not used for relative poses (0 = no limit)",
       0.0, 1.0e4, **RO),
    _p("pose_floor_px", 0.25, "relative poses' covariance: the pixel noise is the inliers' own "
       "(a posteriori), at least this (px): a lower bound only (docs/real-cameras.md)",
       0.0, 100.0, **RO),
    _p("pose_systematic_px", 0.0, "relative poses' covariance: this camera's systematic error "
       "that no residual shows (rolling shutter, a late image stamp), as a rotation std of this "
       "many pixels' angle at the focal length on each axis (docs/real-cameras.md says how to "
       "choose it)", 0.0, 100.0, **RO),
    _p("pose_floor_rotation_deg", 0.0, "... and that rotation std at least this (deg)", 0.0,
       90.0, **RO),
    _p("pose_floor_translation_m", 0.005, "covariance floor: translation std (m), plus ...",
       0.0, 100.0, **RO),
    _p("pose_floor_translation_rel", 0.01, "... this fraction of the translation's length",
       0.0, 10.0, **RO),
    _p("right_image_topic", "", "stereo: sensor_msgs/Image of the right camera, rectified like "
       "the left (image_topic); keyframe depth from StereoSGBM ('' = none)", **RO),
    _p("right_camera_info_topic", "", "stereo: sensor_msgs/CameraInfo of the right camera "
       "(its P gives the baseline)", **RO),
    _p("qos", "sensor_data", "input QoS: sensor_data (best effort, hears every publisher) or "
       "reliable (hears reliable publishers only)", choices=("sensor_data", "reliable"), **RO),
    _p("queue_size", 4, "frames waiting for the worker; when full the oldest is dropped",
       1, 1000, **RO),
    _p("diagnostics_period", 1.0, "seconds between /diagnostics messages", 0.1, 60.0, **RO),
    _p("autosave_period", 0.0, "seconds between saves of a changed map to map_dir (0 = off)",
       0.0, 86400.0, **RO),
    _p("load_map_on_start", False, "load the map in map_dir at start-up (empty if none yet)",
       **RO),
    # ---- a rig of several cameras (start-up only; docs/rig.md)
    _p("cameras", (), "several cameras on one robot, e.g. [front, rear]: one map, loops across "
       "cameras, given between base poses in base_frame; camera <name> has the parameters "
       "<name>.image_topic (default <name>/image), .camera_info_topic (<name>/camera_info), "
       ".depth_topic, .right_image_topic, .right_camera_info_topic, .frame_id and "
       ".camera_to_base (x, y, z, qx, qy, qz, qw; unset: from /tf_static); empty = the one "
       "camera of image_topic", strings=True, **RO),
    _p("base_frame", "base_link", "rig: the robot frame its loops are given in, the parent of "
       "each camera_to_base", **RO),
    _p("rig_stamp_tolerance", 0.02, "rig: frames of its cameras stamped within this many "
       "seconds form one rig keyframe (encoded as one batch)", 0.0, 1.0, **RO),
    _p("rig_max_delay", 0.2, "rig: how long (s, wall clock) a rig keyframe waits for a late "
       "camera before it goes on without it (counted in /diagnostics)", 0.0, 10.0, **RO),
    _p("rig_tf_wait", 5.0, "rig: at start-up, how long (s) to wait for /tf_static to give the "
       "camera_to_base of cameras without one (needs the tf2_msgs package)", 0.0, 60.0, **RO),
    # ---- identity and prior maps (start-up only; docs/fleet.md)
    _p("robot_id", "", "robot of every keyframe and loop ('' = the node's namespace without "
       f"slashes, else '{DEFAULT_ROBOT}'); {RULE}", **RO),
    _p("session_id", "", "session of every keyframe and loop ('' = the start time, UTC, "
       f"YYYYMMDDTHHMMSSZ); {RULE}; must not name a session of this robot in a prior map",
       **RO),
    _p("prior_map_dirs", (), "saved place maps loaded read-only at start-up and searched with "
       "the live map (e.g. earlier sessions or other robots); never written", strings=True,
       **RO),
    # ---- run time
    _p("save_on_shutdown", False, "save the map to map_dir when the node stops"),
    _p("map_dir", "", "map folder of the save_map / load_map / build_map services"),
    _p("build_source", "", "build_map input: a rosbag (folder, .mcap, .db3, .bag) or an image "
       "folder (sorted by name)"),
    _p("build_image_topic", "", "image topic of a build_source bag ('' = its only one)"),
    _p("build_image_period", 1.0, "seconds between the synthetic stamps of folder images",
       0.001, 3600.0),
    _p("max_image_pixels", MAX_PIXELS, "images larger than this (width * height) are skipped "
       "before decoding (a small PNG can claim 20000 x 20000)", 1, 1 << 30),
    _p("pose_tolerance", 0.2, "largest stamp gap (s) between a frame and its pose", 0.0, 60.0),
    _p("publish_rejected", False, "also publish rejected best candidates on the detail and json "
       "topics (accepted = 0)"),
    _p("marker_frame_id", "map", "frame of the loop-closure markers (the poses' frame)"),
    _p("loop_image", True, "publish loop_closure/image (sensor_msgs/Image, bgr8) for each "
       "accepted loop: query | match side by side, the verified inlier matches drawn, the "
       "score and pose written on it (RViz2 and Foxglove show it); false = off, and no "
       "keyframe image is kept"),
    _p("loop_image_rejected", False, "with loop_image: also for the best candidate of each "
       "rejected keyframe, with the reason written on it"),
    _p("loop_image_memory_mb", 64, "MB of JPEG keyframe images kept for loop_image's match side "
       "(longer side 320 px, ~10-20 KB a keyframe); when full the oldest go and a loop to one "
       "of them shows 'no image' (a loaded or prior map's keyframes have none)", 0, 100000,
       **RO),
    # ---- detector (run time)
    _p("mode", "mapping", "mapping: query, then add keyframes; localization: query only",
       choices=("mapping", "localization")),
    _p("map_growth", "places", "mapping: places = a keyframe that an accepted loop with a metric "
       "pose ties to a stored keyframe of the same appearance (or one linked to it) is not "
       "stored again, only counted with its representative (its loops are published as "
       "found): the map grows with places and appearances, not hours; all = store every "
       "keyframe (docs/map-storage.md, growth)", choices=("places", "all")),
    _p("preset", "speed", "detector preset (speed: top_k 10, min_frame_interval 0.2; "
       "performance: top_k 100, min_frame_interval 0)", choices=("speed", "performance")),
    _p("top_k", 0, "candidates re-ranked per keyframe (0 = the preset's)", 0, 1000),
    _p("rerank_budget_ms", 0.0, "latency budget of re-ranking per keyframe, ms: candidates are "
       "scored best-global first until the next step would overrun it (the global best always "
       "is); the record's 'scored' says how many. 0 = no budget: all top_k", 0.0, 600000.0),
    _p("rerank_cascade", False, "score each candidate one direction first (the query first) "
       "and the second only where it can still change the decision (its bound, learned from "
       "the pairs scored both ways, reaches score_threshold and the best score so far): the "
       "same loops from about half the decoder passes on the demo worlds (docs/performance.md); "
       "false = every candidate both ways, as the paper"),
    _p("learned_floor", True, "with rerank_cascade: skip re-ranking a keyframe whose best global "
       "similarity lies below the floor learned from this map's accepted loops (their 1st "
       "percentile - 0.05); never before 50 loops were accepted in the map, nor while a loop "
       "may be continued (sequence_margin)"),
    _p("score_threshold", 0.0, "accept when the re-rank score (logit(q,c) + logit(c,q) + "
       "global_weight x global similarity) >= this", -1.0e6, 1.0e6),
    _p("global_weight", 0.0, "re-rank by pair score + this x global similarity (cosine); 0 = "
       "the pair score alone, as the paper. For a weak pair classifier (config/demo.yaml)",
       0.0, 1.0e4),
    _p("global_floor", -1.0, "skip re-ranking below this global similarity (-1 = off)",
       -1.0, 1.0),
    _p("min_frame_interval", -1.0, "skip frames closer than this (s) to the last encoded one "
       "(-1 = the preset's)", -1.0, 3600.0),
    _p("keyframe_max_similarity", 0.98, "a frame this similar to the last keyframe is skipped",
       -1.0, 1.0),
    _p("exclude_recent_s", 30.0, "never match keyframes stamped within this many seconds of the "
       "query, before or after it (a bag played again, a clock reset)", 0.0, 86400.0),
    _p("exclude_recent_keyframes", 10, "... nor among the newest this many", 0, 1000000),
    _p("temporal_consistency", 1, "accept after this many consecutive agreeing queries", 1, 100),
    _p("temporal_tolerance", 5, "agreeing: matched ids within this many keyframes", 0, 100000),
    _p("sequence_margin", 0.0, "when the best candidate scores below score_threshold, accept "
       "one that continues the previous keyframe's accepted loop (same map, robot and session, "
       "id within temporal_tolerance) at score_threshold - this (verification still applies); "
       "0 = off", 0.0, 1.0e6),
    _p("geometric_verification", False, "also require ORB + fundamental-matrix RANSAC inliers"),
    _p("min_inliers", 15, "inliers needed with geometric_verification", 0, 100000),
    _p("loop_per_map", True, "with prior_map_dirs: search the live map and each prior map for "
       "top_k candidates on its own and accept at most one loop per map (a keyframe can close "
       "loops into its own earlier session and other robots' maps at once; re-ranks up to "
       "top_k x maps, rerank_budget_ms per map); false = one top_k of all maps, one loop. "
       "Without prior maps both are the same"),
)  # fmt: skip

PARAMS += tuple(  # fleet exchange: all start-up only; a row may end with keyword arguments
    _p(*row[:-1], **RO, **row[-1]) if isinstance(row[-1], dict) else _p(*row, **RO)
    for row in FLEET_PARAMS
)
SPECS: dict[str, ParamSpec] = {p.name: p for p in PARAMS}
DETECTOR_PARAMS = (
    "mode",
    "map_growth",
    "preset",
    "top_k",
    "rerank_budget_ms",
    "rerank_cascade",
    "learned_floor",
    "score_threshold",
    "global_weight",
    "global_floor",
    "min_frame_interval",
    "keyframe_max_similarity",
    "exclude_recent_s",
    "exclude_recent_keyframes",
    "temporal_consistency",
    "temporal_tolerance",
    "sequence_margin",
    "geometric_verification",
    "min_inliers",
    "loop_per_map",
)
