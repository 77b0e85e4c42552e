"""Replay a rosbag through the node's `LoopClosurePipeline` and report (`pairvpr-bag-replay`'s
library function; the command line is ``offline.replay.cli``).

Writes into ``--out`` (default ``replay_out/``): ``loops.csv`` / ``loops.json`` (one record per
queried keyframe, accepted or not), ``summary.json``, the place map in ``map/`` (loadable by the
node's load-map service, ``PlaceMap.load``), ``pr_curve.png`` and ``trajectory.png`` when the bag
has poses, and with ``--write-bag`` a rosbag2 (mcap) folder ``bag/`` holding the image topic and
the node's loop-closure topics at the original receive times. If reading stops part-way (corrupt
bag, Ctrl-C), everything processed so far is still written and the exit status is 1 (130 for
Ctrl-C).
"""

from __future__ import annotations

import json
import time
from contextlib import nullcontext
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pair_vpr_ros.errors import OutputError, PairVPRError
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.identity import resolve_identity
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.prior_maps import open_prior_maps
from pair_vpr_ros.model import PairVPRModel
from pair_vpr_ros.offline.bags import reader as bag_io
from pair_vpr_ros.offline.bags.calibration import calibration_loader
from pair_vpr_ros.offline.bags.geometry import attach, open_geometry
from pair_vpr_ros.offline.bags.loop_writer import LoopBagWriter
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.bags.pose_topics import choose_pose_topics
from pair_vpr_ros.offline.bags.stereo import with_right
from pair_vpr_ros.offline.replay import notes as replay_notes
from pair_vpr_ros.offline.replay.drive import ReplayRun, drive
from pair_vpr_ros.offline.replay.options import ReplayOptions, ReplaySummary
from pair_vpr_ros.offline.replay.outputs import check_map_dir, prepare_out
from pair_vpr_ros.offline.report.folder import check_writable, write_report
from pair_vpr_ros.offline.report.loop_truth import KeyframeInfo
from pair_vpr_ros.offline.report.prior_truth import evaluate_prior_loops, prior_positions
from pair_vpr_ros.types import PoseTrack
from pair_vpr_ros.weights import Weights, check_runtime, load_model


def _keyframes(
    pipe: LoopClosurePipeline, run: ReplayRun, truth: PoseTrack | None, tolerance: float
) -> list[KeyframeInfo]:
    """Every keyframe with its ground-truth pose (not the odometry the map keeps), those the
    map did not store (map_growth places) too: queries all the same (loop_truth)."""

    def pose_at(stamp: float) -> tuple | None:
        pose = truth.nearest(stamp, tolerance) if truth is not None else None
        return tuple(pose) if pose is not None else None

    out = [KeyframeInfo(m.id, m.stamp, pose_at(m.stamp)) for m in pipe.place_map.all_meta()]
    out += [KeyframeInfo(n, t, pose_at(t), stored=False) for t, n in run.represented]
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


def replay_bag(
    bag: str | Path,
    out_dir: str | Path = "replay_out",
    options: ReplayOptions | None = None,
    *,
    model: PairVPRModel | None = None,
    weights: str | Path | Weights | None = None,
    config: DetectorConfig | None = None,
    geometry: GeometryConfig | None = None,
) -> ReplaySummary:
    """Replay the image topic of ``bag`` through a ``LoopClosurePipeline`` into ``out_dir``.

    ``options``: topics, tolerances and outputs (``ReplayOptions``). ``model`` gives the network,
    else ``weights`` (a checkpoint path; None: found as ``weights.resolve_weights`` says) loaded
    on ``options.device`` with ``options.precision`` and ``options.backend``. ``config``: the
    detector (acceptance, top-K); ``geometry``: feature and relative-pose settings. Raises
    ``PairVPRError`` subclasses for bad input, before the bag is read where possible; a failure
    part-way is returned in ``error``, with everything
    processed before it written.
    """
    config, o = config or DetectorConfig(), options or ReplayOptions()
    o.check()
    out = Path(out_dir)
    check_writable(out, "output folder")
    if o.save_map:
        check_writable(o.map_path(out), "map folder")
    folder = check_map_dir(o.map_path(out), o.overwrite) if o.save_map else None
    try:  # the map folder's lock is held until the save (another writer is refused now)
        return _replay(bag, out, o, folder, model, weights, config, geometry)
    finally:
        if folder is not None:
            folder.release()


def _replay(bag, out: Path, o: ReplayOptions, folder, model, weights, config, geometry):
    """`replay_bag` once its outputs are checked; `folder`: the map folder (lock held)."""
    identity = resolve_identity(o.robot_id, o.session_id)
    calibration_notes: list[str] = []
    if model is None:
        check_runtime(o.device, o.precision, o.backend)
        calibration = calibration_loader(
            o.openvino_calibration, o.openvino_calibration_topic, o.max_image_pixels,
            calibration_notes.append,
        )  # fmt: skip
    with open_bag(bag) as reader:
        topic = bag_io.choose_image_topic(reader, o.topic)
        found = bag_io.topics_of_types(reader, bag_io.POSE_TYPES)
        chosen = choose_pose_topics(found, o.pose_topic, o.gt_topic, Path(bag).name)
        summary = ReplaySummary(str(bag), topic, chosen.pose, chosen.gt, out_dir=str(out))
        summary.warnings += [chosen.warning] if chosen.warning else []
        poses = _read_pose_topic(reader, summary, chosen.pose)
        truth = poses if chosen.gt == chosen.pose else _read_pose_topic(reader, summary, chosen.gt)
        bag_out = prepare_out(out, o.write_bag)
        run = ReplayRun(summary)
        geo, summary.depth_topic, summary.camera_info_topic, notes = open_geometry(
            reader, o.depth_topic, o.camera_info_topic, o.depth_tolerance,
            run.counts.geometry_skips,
        )  # fmt: skip
        summary.notes = [*notes, *chosen.notes]
        for note in summary.notes if o.announce is not None else ():
            o.announce(note)
        if model is None:
            model = load_model(
                weights, device=o.device, precision=o.precision, backend=o.backend,
                openvino_cache_dir=o.openvino_cache_dir, openvino_calibration=calibration,
            )  # fmt: skip
            summary.warnings += calibration_notes
        save_to = o.map_path(out) if o.save_map else None
        priors = open_prior_maps(o.prior_maps, model.fingerprint, identity, "--prior-map", save_to)
        pipe = LoopClosurePipeline(
            model, config, index=o.index, geometry=geometry, identity=identity,
            prior_maps=priors.maps,
        )  # fmt: skip
        summary.config = asdict(config)
        summary.model = pipe.model.fingerprint
        summary.robot, summary.session = identity.robot, identity.session
        summary.prior_maps = priors.summary()
        summary.notes += priors.notes
        for note in priors.notes if o.announce is not None else ():
            o.announce(note)
        frames = bag_io.iter_frames(
            reader, topic, poses, o.pose_tolerance, o.max_frames, keep_cdr=o.write_bag,
            max_pixels=o.max_image_pixels,
        )  # fmt: skip
        total = reader.topics[topic].msgcount
        total = min(total, o.max_frames) if o.max_frames is not None else total
        msgtype = reader.topics[topic].msgtype
        writer = LoopBagWriter(bag_out, topic, msgtype) if o.write_bag else None
        summary.warnings += [writer.typed_note] if writer and writer.typed_note else []
        source = attach(run.frames(frames, Path(bag).name), geo)
        source = replay_notes.note_demo_model(with_right(source, reader, o, geo.counts), summary)
        start = time.perf_counter()
        with (
            tqdm(total=total, unit="frame", desc="replay", disable=not o.progress) as bar,
            writer if writer is not None else nullcontext(),
        ):
            drive(run, pipe, source, o.batch_size, writer, bar)
        summary.bag_out = str(bag_out) if writer is not None else None
        summary.seconds = time.perf_counter() - start
    if folder is not None:
        folder.release()  # the save takes the folder's lock itself
    _finish(run, pipe, out, o, (truth, poses, Path(bag).name))
    return summary


def _finish(
    run: ReplayRun,
    pipe: LoopClosurePipeline,
    out: Path,
    o: ReplayOptions,
    tracks: tuple[PoseTrack | None, PoseTrack | None, str],
) -> None:
    """Save the map, write the report and summary.json (also after a failure part-way).
    `tracks`: the bag's ground truth, its pose topic and its name (prior maps' keyframes)."""
    summary, counts = run.summary, run.counts
    truth = tracks[0]
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
    summary.warnings += pipe.geometry.camera_warnings  # once per camera (lens distortion)
    summary.candidates = len(run.records)
    summary.pipeline_counts = pipe.counts.to_dict()
    try:
        if o.save_map:
            summary.map_dir = str(pipe.save_map(o.map_path(out), overwrite=o.overwrite))
        keyframes = _keyframes(pipe, run, truth, o.pose_tolerance)
        has_poses = any(k.pose is not None for k in keyframes)
        global_top1 = run.global_top1 if has_poses else None
        evaluation = write_report(
            out, run.records, keyframes, _path(run.stamps, truth, o.pose_tolerance), o.gt_radius,
            pipe.config.exclude_recent_s, global_top1, source=summary.gt_topic or "",
            global_weight=pipe.config.global_weight,
        )  # fmt: skip
        if evaluation is not None:
            summary.loop_evaluation = evaluation
            summary.evaluation = {**evaluation.to_dict(), "gt_topic": summary.gt_topic}
            summary.warnings += replay_notes.exclusion_notes(keyframes, evaluation)
            if pipe.maps.priors:
                metas = [m for prior in pipe.maps.priors for m in prior.all_meta()]
                covered = prior_positions(metas, tracks[2], truth, tracks[1], o.pose_tolerance)
                summary.prior_evaluation = evaluate_prior_loops(
                    run.records, keyframes, covered, len(metas), o.gt_radius
                ).to_dict()
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
