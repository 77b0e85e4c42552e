"""`pairvpr-bag-replay`: run a rosbag through the node's `LoopClosurePipeline` and report.

Writes into ``--out`` (default ``replay_out/``): ``loops.csv`` / ``loops.json`` (one record per
queried keyframe, accepted or not), ``summary.json``, the place map in ``map/`` (loadable by the
node's load-map service, ``PlaceMap.load``), ``pr_curve.png`` and ``trajectory.png`` when the bag
has poses, and with ``--write-bag`` a rosbag2 (mcap) folder ``bag/`` holding the image topic and
the node's loop-closure topics at the original receive times. If reading stops part-way (corrupt
bag, Ctrl-C), everything processed so far is still written and the exit status is 1.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections import Counter, deque
from collections.abc import Iterator
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pair_vpr_ros import bag_io
from pair_vpr_ros.bag_io import BagFrame, LoopBagWriter
from pair_vpr_ros.detector import Candidate, DetectorConfig, LoopRecord
from pair_vpr_ros.devices import check_device
from pair_vpr_ros.errors import BagError, ConfigError, PairVPRError
from pair_vpr_ros.model import load_pairvpr
from pair_vpr_ros.node_params import detector_config, read_params_file
from pair_vpr_ros.pipeline import Frame, LoopClosurePipeline
from pair_vpr_ros.report import KeyframeInfo, write_report

NONE = "none"  # --pose-topic none / --map-dir none


@dataclass
class ReplaySummary:
    """What one replay did; ``error`` says where it stopped when it did not finish."""

    bag: str
    topic: str
    pose_topic: str | None
    frames: int = 0  # image messages read
    skipped: int = 0  # messages that did not deserialise or convert
    skip_reasons: dict[str, int] = field(default_factory=dict)  # up to 10 distinct reasons
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
    error: str | None = None

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
    pending: deque[BagFrame] = field(default_factory=deque)
    reasons: Counter[str] = field(default_factory=Counter)
    records: list[LoopRecord] = field(default_factory=list)
    global_top1: list[LoopRecord] = field(default_factory=list)  # global-only baseline
    positions: list[tuple[float, float, float]] = field(default_factory=list)


def _frames(run: _Run, frames: Iterator[BagFrame], source: str) -> Iterator[Frame]:
    """Bag frames -> pipeline frames; skips bad ones and ends quietly on a read error (kept in
    ``run.summary.error``) so the pipeline still flushes the frames it holds."""
    try:
        for bf in frames:
            run.summary.frames += 1
            if bf.pose is not None:
                run.positions.append(bf.pose[:3])
            if bf.rgb is None:
                run.summary.skipped += 1
                run.reasons[bf.error or "unknown"] += 1
                continue
            run.pending.append(bf)
            yield Frame(bf.stamp, bf.rgb, bf.frame_id, bf.pose, f"{source}#{bf.index}")
    except BagError as err:
        run.summary.error = str(err)


def _load_model(weights: str | Path | None, model: Any, device: str) -> Any:
    if model is not None:
        return model
    if weights is None:
        raise ConfigError(
            "no model: pass --weights PATH (a Pair-VPR checkpoint such as pairvpr-vitB.pth)"
        )
    return load_pairvpr(weights, device=device)


def _global_top1(record: LoopRecord, best: Candidate) -> LoopRecord:
    """The record ranking by global similarity alone would give: the top FAISS candidate."""
    return replace(
        record, match_id=best.id, match_stamp=best.stamp, match_frame_id=best.frame_id,
        global_similarity=best.global_similarity, pair_score=float("nan"), rank_before=1,
        rank_after=1, accepted=False, reason="global top-1",
    )  # fmt: skip


def _keyframes(
    pipe: LoopClosurePipeline, poses: bag_io.PoseTrack | None, tolerance: float
) -> list[KeyframeInfo]:
    out = []
    for meta in pipe.place_map.all_meta():
        pose = meta.pose
        if pose is None and poses is not None:
            pose = poses.nearest(meta.stamp, tolerance)
        out.append(KeyframeInfo(meta.id, meta.stamp, tuple(pose) if pose is not None else None))
    return out


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
            bar.update(summary.frames - bar.n)
            bar.set_postfix(keyframes=summary.keyframes, loops=summary.loops, refresh=False)
    except KeyboardInterrupt:
        summary.error = f"interrupted after {summary.frames} image messages"


def _prepare_out(out: Path, write_bag: bool) -> Path:
    out.mkdir(parents=True, exist_ok=True)
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
    weights: str | Path | None = None,
    model: Any = None,
    topic: str | None = None,
    pose_topic: str | None = None,
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
) -> ReplaySummary:
    """Replay the image topic of ``bag`` through a ``LoopClosurePipeline`` into ``out_dir``.

    ``model`` (a ``PairVPR``) or ``weights`` (checkpoint path) give the network. ``topic``: image
    topic (needed when the bag has several). ``pose_topic``: None picks the bag's only pose
    topic, ``"none"`` ignores poses. ``map_dir`` defaults to ``out_dir/map``. Raises
    ``PairVPRError`` subclasses for bad input; a failure part-way is returned in ``error``.
    """
    config = config or DetectorConfig()
    out = Path(out_dir)
    if device != "cpu" and model is None:
        check_device(device)
    with bag_io.open_bag(bag) as reader:
        topic = bag_io.choose_image_topic(reader, topic)
        summary = ReplaySummary(str(bag), topic, None, out_dir=str(out))
        if pose_topic != NONE:
            summary.pose_topic = bag_io.choose_pose_topic(reader, pose_topic)
        found = bag_io.topics_of_types(reader, bag_io.POSE_TYPES)
        if pose_topic is None and len(found) > 1:
            summary.warnings.append(
                f"no ground truth: several pose topics ({', '.join(found)}); pick one with "
                "--pose-topic"
            )
        poses = bag_io.read_poses(reader, summary.pose_topic) if summary.pose_topic else None
        if poses is not None and poses.error:
            summary.warnings.append(poses.error)
        bag_out = _prepare_out(out, write_bag)
        pipe = LoopClosurePipeline(_load_model(weights, model, device), config)
        summary.config = asdict(config)
        summary.model = pipe.model.fingerprint
        run = _Run(summary)
        frames = bag_io.iter_frames(
            reader, topic, poses, pose_tolerance, max_frames, keep_cdr=write_bag
        )
        total = reader.topics[topic].msgcount
        total = min(total, max_frames) if max_frames is not None else total
        writer = LoopBagWriter(bag_out, topic, reader.topics[topic].msgtype) if write_bag else None
        source = _frames(run, frames, Path(bag).name)
        start = time.perf_counter()
        with (
            tqdm(total=total, unit="frame", desc="replay", disable=not progress) as bar,
            writer if writer is not None else nullcontext(),
        ):
            _drive(run, pipe, source, batch_size, writer, bar)
        summary.bag_out = str(bag_out) if writer is not None else None
        summary.seconds = time.perf_counter() - start
    _finish(run, pipe, out, map_dir, save_map, gt_radius, poses, pose_tolerance)
    return summary


def _finish(
    run: _Run,
    pipe: LoopClosurePipeline,
    out: Path,
    map_dir: str | Path | None,
    save_map: bool,
    gt_radius: float,
    poses: bag_io.PoseTrack | None,
    pose_tolerance: float,
) -> None:
    """Save the map, write the report and summary.json (also after a failure part-way)."""
    summary = run.summary
    summary.fps = summary.frames / summary.seconds if summary.seconds > 0 else 0.0
    summary.skip_reasons = dict(run.reasons.most_common(10))
    if summary.frames and summary.skipped == summary.frames:
        first = next(iter(summary.skip_reasons))
        summary.warnings.append(f"no image of {summary.topic} could be used, e.g.: {first}")
    summary.candidates = len(run.records)
    summary.pipeline_counts = dict(pipe.counts)
    try:
        if save_map:
            summary.map_dir = str(pipe.save_map(Path(map_dir) if map_dir else out / "map"))
        keyframes = _keyframes(pipe, poses, pose_tolerance)
        has_poses = any(k.pose is not None for k in keyframes)
        global_top1 = run.global_top1 if has_poses else None
        positions = np.asarray(run.positions, dtype=np.float64).reshape(-1, 3)
        evaluation = write_report(
            out, run.records, keyframes, positions, gt_radius, pipe.config.exclude_recent_s,
            global_top1,
        )  # fmt: skip
        summary.evaluation = evaluation.to_dict() if evaluation is not None else None
    except PairVPRError as err:
        summary.error = summary.error or str(err)
    finally:
        pipe.close()
        (out / "summary.json").write_text(json.dumps(summary.to_dict(), indent=1) + "\n")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pairvpr-bag-replay",
        description="Replay a rosbag's camera topic through the Pair-VPR loop-closure pipeline "
        "(the same one vpr_node runs) and write loops, the place map and an evaluation report.",
    )
    p.add_argument("bag", help="rosbag2 folder (mcap or sqlite3), .mcap / .db3 file or ROS 1 .bag")
    p.add_argument("--weights", metavar="PATH", required=True, help="Pair-VPR checkpoint (.pth)")
    p.add_argument(
        "--out", metavar="DIR", default="replay_out", help="output folder (default: %(default)s)"
    )
    p.add_argument(
        "--topic", help="image topic (Image or CompressedImage); needed when the bag has several"
    )
    p.add_argument(
        "--pose-topic",
        help="Odometry / PoseStamped / PoseWithCovarianceStamped topic for ground truth "
        "(default: the bag's only pose topic; 'none' to ignore poses)",
    )
    p.add_argument(
        "--gt-radius",
        type=float,
        default=10.0,
        metavar="M",
        help="a loop is true when its keyframes lie within M metres (default: %(default)s)",
    )
    p.add_argument(
        "--threshold", type=float, help="pair-score acceptance threshold (default: detector's)"
    )
    p.add_argument(
        "--params-file",
        type=Path,
        help="take the detector settings from a vpr_node parameter file "
        "(e.g. config/vpr_node.yaml); --threshold and --top-k still override",
    )
    p.add_argument(
        "--top-k",
        type=_positive_int,
        help="candidates re-ranked per keyframe (default: detector's)",
    )
    p.add_argument(
        "--device", default="cpu", help="torch device: cpu, cuda, cuda:1 (default: %(default)s)"
    )
    p.add_argument(
        "--batch-size",
        type=_positive_int,
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
        help="where to save the place map (default: OUT/map; 'none' to not save it)",
    )
    p.add_argument("--max-frames", type=_positive_int, help="stop after this many image messages")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3f}"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    overrides = {"score_threshold": args.threshold, "top_k": args.top_k}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    try:
        if args.params_file is not None:
            config = detector_config(read_params_file(args.params_file)).updated(**overrides)
        else:
            config = DetectorConfig(**overrides)
        summary = replay_bag(
            args.bag, args.out, weights=args.weights, topic=args.topic, pose_topic=args.pose_topic,
            config=config, write_bag=args.write_bag, gt_radius=args.gt_radius, device=args.device,
            batch_size=args.batch_size, map_dir=None if args.map_dir == NONE else args.map_dir,
            save_map=args.map_dir != NONE, max_frames=args.max_frames, progress=not args.quiet,
        )  # fmt: skip
    except PairVPRError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    for warning in summary.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    ev = summary.evaluation
    if ev is not None:
        print(
            f"precision {_fmt(ev['precision'])}, recall {_fmt(ev['recall'])} "
            f"({ev['positives']} keyframes with a true match within {ev['gt_radius_m']} m)"
        )
    print(f"outputs in {summary.out_dir}")
    print(summary.line())
    if summary.error:
        print(f"error: {summary.error} (what was processed before is written)", file=sys.stderr)
        return 1
    return 0
