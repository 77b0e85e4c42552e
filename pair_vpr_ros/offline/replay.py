"""`pairvpr-bag-replay`: run a rosbag through the node's `LoopClosurePipeline` and report.

Writes into ``--out`` (default ``replay_out/``): ``loops.csv`` / ``loops.json`` (one record per
queried keyframe, accepted or not), ``summary.json``, the place map in ``map/`` (loadable by the
node's load-map service, ``PlaceMap.load``), ``pr_curve.png`` and ``trajectory.png`` when the bag
has poses, and with ``--write-bag`` a rosbag2 (mcap) folder ``bag/`` holding the image topic and
the node's loop-closure topics at the original receive times. If reading stops part-way (corrupt
bag, Ctrl-C), everything processed so far is still written and the exit status is 1 (130 for
Ctrl-C).
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from collections import deque
from collections.abc import Iterator
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pair_vpr_ros.cli import (
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    EXIT_OK,
    finite_float,
    float_flag,
    positive_int,
    run_cli,
)
from pair_vpr_ros.detector import Candidate, DetectorConfig, LoopRecord
from pair_vpr_ros.devices import check_device
from pair_vpr_ros.errors import ConfigError, MapError, OutputError, PairVPRError
from pair_vpr_ros.geometry.features import KINDS
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.imaging import MAX_PIXELS
from pair_vpr_ros.model import PairVPRModel
from pair_vpr_ros.offline import bag_io
from pair_vpr_ros.offline.bag_geometry import attach, open_geometry
from pair_vpr_ros.offline.bag_io import BagFrame, LoopBagWriter
from pair_vpr_ros.offline.pose_topics import choose_pose_topics
from pair_vpr_ros.offline.report import KeyframeInfo, write_report
from pair_vpr_ros.offline.sources import FrameCounts, bag_frames
from pair_vpr_ros.params import detector_config, read_params_file
from pair_vpr_ros.pipeline import Frame, LoopClosurePipeline
from pair_vpr_ros.place_map.files import LOCK_NAME, DirLock
from pair_vpr_ros.place_map.manifest import MANIFEST_NAME, read_manifest
from pair_vpr_ros.types import PoseTrack
from pair_vpr_ros.weights import Weights, load_model, resolve_weights

NONE = "none"  # --pose-topic none / --map-dir none
DEPTH_TOLERANCE = float_flag("a number of seconds in [0, 1]", lambda v: 0 <= v <= 1)


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
    evaluation: dict[str, Any] | None = None
    config: dict[str, Any] = field(default_factory=dict)  # the DetectorConfig used
    model: str = ""  # the model's fingerprint (weights, input size, descriptor size)
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # how each topic was picked
    error: str | None = None
    interrupted: bool = False  # stopped by Ctrl-C (``error`` says after how many messages)

    def line(self) -> str:
        return (
            f"frames {self.frames}, keyframes {self.keyframes}, loops {self.loops}, "
            f"skipped {self.skipped}, {self.seconds:.1f} s, {self.fps:.1f} frames/s"
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class _Run:
    """State of one replay loop (frames in flight between the reader and the pipeline)."""

    summary: ReplaySummary
    counts: FrameCounts = field(default_factory=FrameCounts)
    pending: deque[BagFrame] = field(default_factory=deque)
    records: list[LoopRecord] = field(default_factory=list)
    global_top1: list[LoopRecord] = field(default_factory=list)  # global-only baseline
    stamps: list[float] = field(default_factory=list)  # of every image read: the plotted path

    def frames(self, read: Iterator[BagFrame], source: str) -> Iterator[Frame]:
        """Usable frames for the pipeline, each kept in ``pending`` until its outcome comes;
        the stamp of every frame read is noted (its ground-truth position is the path)."""

        def noting_stamps() -> Iterator[BagFrame]:
            for bf in read:
                self.stamps.append(bf.stamp)
                yield bf

        for frame, bf in bag_frames(noting_stamps(), self.counts, source):
            self.pending.append(bf)
            yield frame


def _global_top1(record: LoopRecord, best: Candidate) -> LoopRecord:
    """The record ranking by global similarity alone would give: the top FAISS candidate."""
    return replace(
        record, match_id=best.id, match_stamp=best.stamp, match_frame_id=best.frame_id,
        global_similarity=best.global_similarity, pair_score=float("nan"), rank_before=1,
        rank_after=1, accepted=False, reason="global top-1",
    )  # fmt: skip


def _keyframes(
    pipe: LoopClosurePipeline, truth: PoseTrack | None, tolerance: float
) -> list[KeyframeInfo]:
    """Every keyframe with its ground-truth pose (not the odometry the map keeps)."""
    out = []
    for meta in pipe.place_map.all_meta():
        pose = truth.nearest(meta.stamp, tolerance) if truth is not None else None
        out.append(KeyframeInfo(meta.id, meta.stamp, tuple(pose) if pose is not None else None))
    return out


def _path(stamps: list[float], truth: PoseTrack | None, tolerance: float) -> np.ndarray:
    """Ground-truth positions ``[F, 3]`` of the frames read that have one, in order."""
    found = [truth.nearest(t, tolerance) for t in stamps] if truth is not None else []
    return np.asarray([p[:3] for p in found if p is not None], dtype=np.float64).reshape(-1, 3)


def _read_pose_topic(reader: Any, summary: ReplaySummary, topic: str | None) -> PoseTrack | None:
    """The poses of ``topic`` (None: not used); read problems go to the summary's warnings."""
    if topic is None:
        return None
    track, error = bag_io.read_poses(reader, topic)
    bad = bag_io.bad_poses_warning(track, topic)
    summary.bad_poses += track.rejected
    summary.warnings += [w for w in (error, bad) if w]
    return track


def _drive(
    run: _Run,
    pipe: LoopClosurePipeline,
    frames: Iterator[Frame],
    batch_size: int,
    writer: LoopBagWriter | None,
    bar: tqdm,
) -> None:
    """Pipeline outcomes -> records, counts, output bag; Ctrl-C stops like a read error."""
    summary = run.summary
    try:
        for outcome in pipe.process_many(frames, batch_size=batch_size):
            bf = run.pending.popleft()
            assert abs(bf.stamp - outcome.stamp) < 1e-9, "outcomes must come in frame order"
            if outcome.keyframe_id is not None:
                summary.keyframes += 1
            if writer is not None and bf.cdr is not None:
                writer.write_image(bf.cdr, bf.log_time_ns)
            if outcome.loop is not None:
                run.records.append(outcome.loop)
                if outcome.loop.query_id >= 0:
                    run.global_top1.append(_global_top1(outcome.loop, outcome.candidates[0]))
                if outcome.loop.accepted:
                    summary.loops += 1
                    if writer is not None:
                        writer.write_loop(outcome.loop, bf.log_time_ns)
            bar.update(run.counts.frames - bar.n)
            bar.set_postfix(keyframes=summary.keyframes, loops=summary.loops, refresh=False)
    except KeyboardInterrupt:
        summary.error = f"interrupted after {run.counts.frames} image messages"
        summary.interrupted = True
    except PairVPRError as err:  # the output bag or the map could not be written (disk full)
        summary.error = f"stopped after {run.counts.frames} image messages: {err}"


def _check_writable(path: Path, what: str) -> None:
    """`path` (a folder, created later if missing) can be written: OutputError otherwise."""
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        where = "" if existing == path else f" ({existing} is a file)"
        raise OutputError(f"{what} {path} is not a folder{where}: give a folder")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as err:
        raise OutputError(
            f"cannot write {what} {path}: {existing} is not writable ({err.strerror}); pick a "
            "writable folder"
        ) from err


def _check_map_dir(path: Path, overwrite: bool) -> None:
    """Refuse to replace a saved map, or to fill a folder of other files, unless `overwrite`;
    a map another program has open for writing is refused now rather than after the run."""
    if not path.is_dir() or overwrite and not (path / MANIFEST_NAME).exists():
        return
    if (path / MANIFEST_NAME).exists():
        if not overwrite:
            try:
                m = read_manifest(path)
                what = f"{m.count} keyframes, model {m.fingerprint}"
            except MapError:
                what = "damaged"
            raise OutputError(
                f"map folder {path} holds a saved place map ({what}) that this replay would "
                "replace: pass --overwrite to replace it, or --map-dir NEW_FOLDER (to add to a "
                "map, load it in vpr_node and play the bag)"
            )
        DirLock(path).release()  # MapError when another PlaceMap writes there
    elif any(p.name != LOCK_NAME for p in path.iterdir()):
        raise OutputError(
            f"map folder {path} holds other files and no saved map: give a new or empty folder "
            "(or pass --overwrite to save the map beside them)"
        )


def _prepare_out(out: Path, write_bag: bool) -> Path:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputError(f"cannot create the output folder {out}: {err.strerror}") from err
    for stale in ("pr_curve.png", "trajectory.png"):  # a previous run's plots would mislead
        (out / stale).unlink(missing_ok=True)
    bag_out = out / "bag"
    if write_bag and bag_out.exists():
        if not (bag_out / "metadata.yaml").is_file():
            raise ConfigError(f"{bag_out} exists and is not a bag of an earlier replay: move it")
        shutil.rmtree(bag_out)
    return bag_out


def replay_bag(
    bag: str | Path,
    out_dir: str | Path = "replay_out",
    weights: str | Path | Weights | None = None,
    model: PairVPRModel | None = None,
    topic: str | None = None,
    pose_topic: str | None = None,
    gt_topic: str | None = None,
    config: DetectorConfig | None = None,
    write_bag: bool = False,
    gt_radius: float = 10.0,
    device: str = "cpu",
    batch_size: int = 8,
    map_dir: str | Path | None = None,
    save_map: bool = True,
    max_frames: int | None = None,
    pose_tolerance: float = 0.2,
    progress: bool = True,
    overwrite: bool = False,
    max_image_pixels: int = MAX_PIXELS,
    depth_topic: str | None = None,
    camera_info_topic: str | None = None,
    depth_tolerance: float = 0.02,
    geometry: GeometryConfig | None = None,
) -> ReplaySummary:
    """Replay the image topic of ``bag`` through a ``LoopClosurePipeline`` into ``out_dir``.

    ``model`` gives the network, else ``weights`` (a checkpoint path; None: found as
    ``weights.resolve_weights`` says) loaded on ``device``. ``topic``: image topic (needed when
    the bag has several). ``pose_topic`` (attached to keyframes) and
    ``gt_topic`` (the evaluation's ground truth) follow ``pose_topics.choose_pose_topics``:
    None picks by its rules, ``"none"`` uses none. ``depth_topic`` / ``camera_info_topic``:
    None picks the bag's only one, ``"none"`` ignores it; depth is matched to images within
    ``depth_tolerance`` s. ``geometry``: feature and relative-pose settings. ``map_dir``
    defaults to ``out_dir/map``. Raises ``PairVPRError`` subclasses for bad input; a failure
    part-way is returned in ``error``. A saved map (or a folder of other files) at the map
    folder is an ``OutputError`` unless ``overwrite``; outputs that cannot be written are found
    before the bag is read.
    """
    config = config or DetectorConfig()
    out = Path(out_dir)
    if not (math.isfinite(gt_radius) and gt_radius > 0):
        raise ConfigError(f"gt_radius must be a finite number of metres > 0, got {gt_radius}")
    _check_writable(out, "output folder")
    if save_map:
        map_path = Path(map_dir) if map_dir else out / "map"
        _check_writable(map_path, "map folder")
        _check_map_dir(map_path, overwrite)
    if model is None:
        check_device(device)
    with bag_io.open_bag(bag) as reader:
        topic = bag_io.choose_image_topic(reader, topic)
        found = bag_io.topics_of_types(reader, bag_io.POSE_TYPES)
        chosen = choose_pose_topics(found, pose_topic, gt_topic, Path(bag).name)
        summary = ReplaySummary(str(bag), topic, chosen.pose, chosen.gt, out_dir=str(out))
        summary.warnings += [chosen.warning] if chosen.warning else []
        poses = _read_pose_topic(reader, summary, chosen.pose)
        truth = poses if chosen.gt == chosen.pose else _read_pose_topic(reader, summary, chosen.gt)
        bag_out = _prepare_out(out, write_bag)
        model = model if model is not None else load_model(weights, device=device)
        pipe = LoopClosurePipeline(model, config, geometry=geometry)
        summary.config = asdict(config)
        summary.model = pipe.model.fingerprint
        run = _Run(summary)
        geo, summary.depth_topic, summary.camera_info_topic, notes = open_geometry(
            reader, depth_topic, camera_info_topic, depth_tolerance, run.counts.geometry_skips
        )
        summary.notes = [*notes, *chosen.notes]
        frames = bag_io.iter_frames(
            reader, topic, poses, pose_tolerance, max_frames, keep_cdr=write_bag,
            max_pixels=max_image_pixels,
        )  # fmt: skip
        total = reader.topics[topic].msgcount
        total = min(total, max_frames) if max_frames is not None else total
        writer = LoopBagWriter(bag_out, topic, reader.topics[topic].msgtype) if write_bag else None
        source = attach(run.frames(frames, Path(bag).name), geo)
        start = time.perf_counter()
        with (
            tqdm(total=total, unit="frame", desc="replay", disable=not progress) as bar,
            writer if writer is not None else nullcontext(),
        ):
            _drive(run, pipe, source, batch_size, writer, bar)
        summary.bag_out = str(bag_out) if writer is not None else None
        summary.seconds = time.perf_counter() - start
    _finish(run, pipe, out, map_dir, save_map, gt_radius, truth, pose_tolerance)
    return summary


def _finish(
    run: _Run,
    pipe: LoopClosurePipeline,
    out: Path,
    map_dir: str | Path | None,
    save_map: bool,
    gt_radius: float,
    truth: PoseTrack | None,
    pose_tolerance: float,
) -> None:
    """Save the map, write the report and summary.json (also after a failure part-way)."""
    summary, counts = run.summary, run.counts
    summary.frames, summary.skipped = counts.frames, counts.skipped
    summary.error = summary.error or counts.error
    summary.fps = summary.frames / summary.seconds if summary.seconds > 0 else 0.0
    summary.skip_reasons = dict(counts.reasons.most_common(10))
    summary.geometry_skips = dict(counts.geometry_skips.most_common(10))
    if summary.frames and summary.skipped == summary.frames:
        first = next(iter(summary.skip_reasons))
        summary.warnings.append(f"no image of {summary.topic} could be used, e.g.: {first}")
    summary.stamps_backwards, summary.stamps_repeated = counts.backwards, counts.repeated
    summary.warnings += counts.stamp_warnings(summary.topic)
    summary.candidates = len(run.records)
    summary.pipeline_counts = pipe.counts.to_dict()
    try:
        if save_map:
            summary.map_dir = str(pipe.save_map(Path(map_dir) if map_dir else out / "map"))
        keyframes = _keyframes(pipe, truth, pose_tolerance)
        has_poses = any(k.pose is not None for k in keyframes)
        global_top1 = run.global_top1 if has_poses else None
        evaluation = write_report(
            out, run.records, keyframes, _path(run.stamps, truth, pose_tolerance), gt_radius,
            pipe.config.exclude_recent_s, global_top1, source=summary.gt_topic or "",
        )  # fmt: skip
        if evaluation is not None:
            summary.evaluation = {**evaluation.to_dict(), "gt_topic": summary.gt_topic}
    except PairVPRError as err:
        summary.error = summary.error or str(err)
    except OSError as err:  # the report's files (disk full, folder removed meanwhile)
        summary.error = summary.error or f"writing the report to {out} failed: {err}"
    finally:
        pipe.close()
    path = out / "summary.json"
    try:
        path.write_text(json.dumps(summary.to_dict(), indent=1) + "\n")
    except OSError as err:
        raise OutputError(
            f"cannot write {path} ({err.strerror or err}); "
            + (f"the map is saved in {summary.map_dir}" if summary.map_dir else "nothing saved")
        ) from err


POSITIVE_METRES = float_flag("a finite number of metres > 0", lambda v: v > 0)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pairvpr-bag-replay",
        description="Replay a rosbag's camera topic through the Pair-VPR loop-closure pipeline "
        "(the same one vpr_node runs) and write loops, the place map and an evaluation report.",
    )
    p.add_argument("bag", help="rosbag2 folder (mcap or sqlite3), .mcap / .db3 file or ROS 1 .bag")
    p.add_argument(
        "--weights",
        metavar="PATH",
        help="Pair-VPR checkpoint (.pth); default: $PAIRVPR_WEIGHTS, else 'weights' in "
        "--params-file, else the one .pth in $XDG_DATA_HOME/pair_vpr_ros/ "
        "(~/.local/share/pair_vpr_ros/)",
    )
    p.add_argument(
        "--out", metavar="DIR", default="replay_out", help="output folder (default: %(default)s)"
    )
    p.add_argument(
        "--topic", help="image topic (Image or CompressedImage); needed when the bag has several"
    )
    p.add_argument(
        "--pose-topic",
        help="Odometry / PoseStamped / PoseWithCovarianceStamped topic whose poses are attached "
        "to keyframes and saved in the map, like the node's pose_topic (default: the bag's only "
        "pose topic besides --gt-topic; 'none' to attach none)",
    )
    p.add_argument(
        "--gt-topic",
        help="pose topic of ground truth for precision / recall and the plots, kept apart from "
        "--pose-topic because odometry drifts (default: the --pose-topic one; 'none': no "
        "evaluation)",
    )
    p.add_argument(
        "--gt-radius",
        type=POSITIVE_METRES,
        default=10.0,
        metavar="M",
        help="a loop is true when its keyframes lie within M metres (default: %(default)s)",
    )
    p.add_argument(
        "--threshold",
        type=finite_float,
        help="pair-score acceptance threshold (default: detector's)",
    )
    p.add_argument(
        "--params-file",
        type=Path,
        help="take the detector settings from a vpr_node parameter file "
        "(e.g. config/vpr_node.yaml); --threshold and --top-k still override",
    )
    p.add_argument(
        "--top-k",
        type=positive_int,
        help="candidates re-ranked per keyframe (default: detector's)",
    )
    p.add_argument(
        "--device",
        default="cpu",
        help="torch device: cpu, cuda, cuda:1, auto (default: %(default)s)",
    )
    p.add_argument(
        "--batch-size",
        type=positive_int,
        default=8,
        help="frames encoded per batch (default: %(default)s)",
    )
    p.add_argument(
        "--write-bag",
        action="store_true",
        help="also write OUT/bag: images and loop-closure topics",
    )
    p.add_argument(
        "--map-dir",
        metavar="DIR",
        help="where to save the place map (default: OUT/map; 'none' to not save it); a saved "
        "map already there is refused unless --overwrite",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace a saved place map at the map folder (else the replay refuses to start)",
    )
    p.add_argument(
        "--depth-topic",
        help="aligned depth image topic (16UC1 mm / 32FC1 m) for metric relative poses "
        "(default: the bag's only depth image topic; 'none' for monocular poses)",
    )
    p.add_argument(
        "--camera-info-topic",
        help="sensor_msgs/CameraInfo topic of the camera (default: the bag's only one; 'none': "
        "no intrinsics, so no relative poses)",
    )
    p.add_argument(
        "--depth-tolerance",
        type=DEPTH_TOLERANCE,
        default=0.02,
        metavar="S",
        help="largest stamp gap between an image and its depth image (default: %(default)s s)",
    )
    p.add_argument(
        "--features",
        choices=KINDS,
        default="sift",
        help="keypoints for relative poses: sift (accurate) or orb (cheaper) (default: sift)",
    )
    p.add_argument("--max-frames", type=positive_int, help="stop after this many image messages")
    p.add_argument(
        "--max-image-pixels",
        type=positive_int,
        metavar="N",
        help="skip (and count) images larger than N pixels, width x height, before decoding "
        f"(default: --params-file's max_image_pixels, else {MAX_PIXELS:,})",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def main(argv: list[str] | None = None) -> int:
    """Exit codes: `pair_vpr_ros.cli`; a replay stopped part-way by a read error is 1, by
    Ctrl-C 130, with what was processed before written either way."""
    return run_cli(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> int:
    overrides = {"score_threshold": args.threshold, "top_k": args.top_k}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    max_pixels = MAX_PIXELS
    if args.params_file is not None:
        values = read_params_file(args.params_file)
        config = detector_config(values).updated(**overrides)
        max_pixels = values["max_image_pixels"]
    else:
        config = DetectorConfig(**overrides)
    weights = resolve_weights(args.weights, args.params_file)
    summary = replay_bag(
        args.bag, args.out, weights=weights, topic=args.topic, pose_topic=args.pose_topic,
        gt_topic=args.gt_topic, config=config, write_bag=args.write_bag, gt_radius=args.gt_radius,
        device=args.device, batch_size=args.batch_size,
        map_dir=None if args.map_dir == NONE else args.map_dir,
        save_map=args.map_dir != NONE, max_frames=args.max_frames, progress=not args.quiet,
        overwrite=args.overwrite, max_image_pixels=args.max_image_pixels or max_pixels,
        depth_topic=args.depth_topic, camera_info_topic=args.camera_info_topic,
        depth_tolerance=args.depth_tolerance, geometry=GeometryConfig(features=args.features),
    )  # fmt: skip
    for note in summary.notes:
        print(note)
    for warning in summary.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    ev = summary.evaluation
    if ev is not None:
        print(
            f"precision {_fmt(ev['precision'])}, recall {_fmt(ev['recall'])} "
            f"({ev['positives']} keyframes with a true match within {ev['gt_radius_m']} m; "
            f"ground truth {ev['gt_topic']})"
        )
    print(f"outputs in {summary.out_dir}")
    print(summary.line())
    if summary.error:
        print(f"error: {summary.error} (what was processed before is written)", file=sys.stderr)
        return EXIT_INTERRUPTED if summary.interrupted else EXIT_ERROR
    return EXIT_OK
