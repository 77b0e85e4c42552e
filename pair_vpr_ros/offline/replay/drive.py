"""The replay's loop: bag frames through the pipeline, outcomes into records, counts and the
output bag (`ReplayRun`, `drive`); ``offline.replay.replay_bag`` sets it up and writes the results.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace

from tqdm import tqdm

from pair_vpr_ros.errors import OutputError, PairVPRError
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.loops.records import Candidate, LoopRecord
from pair_vpr_ros.loops.rig import Rig
from pair_vpr_ros.loops.rig_frames import RigAssembler
from pair_vpr_ros.messages.loop_image import LoopPictures
from pair_vpr_ros.offline.bags.loop_writer import LoopBagWriter
from pair_vpr_ros.offline.bags.reader import BagFrame
from pair_vpr_ros.offline.bags.sources import FrameCounts, bag_frames
from pair_vpr_ros.offline.replay.options import ReplaySummary
from pair_vpr_ros.offline.report.decision_log import DecisionLog
from pair_vpr_ros.offline.report.html import ReportWriter


@dataclass
class ReplayRun:
    """State of one replay loop (frames in flight between the reader and the pipeline)."""

    summary: ReplaySummary
    counts: FrameCounts = field(default_factory=FrameCounts)
    pending: deque[BagFrame] = field(default_factory=deque)
    records: list[LoopRecord] = field(default_factory=list)
    global_top1: list[LoopRecord] = field(default_factory=list)  # global-only baseline
    stamps: list[float] = field(default_factory=list)  # of every image read: the plotted path
    # keyframes the map did not store (map_growth places): (stamp, keyframes stored before it),
    # queries all the same for the evaluation (report.loop_truth.KeyframeInfo)
    represented: list[tuple[float, int]] = field(default_factory=list)
    rig: object | None = None  # a rig's RigCounts (rig_groups)
    log: DecisionLog = field(default_factory=DecisionLog)  # every decision, compactly
    report: ReportWriter | None = None  # OUT/report/, written as the run goes
    pictures: LoopPictures | None = None  # --write-bag's loop images

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

    def rig_groups(
        self, pairs: Iterable[tuple[Frame, BagFrame]], rig: Rig, cameras: list[FrameCounts]
    ) -> Iterator[list[Frame]]:
        """Every camera's (frame, message), merged by stamp -> rig keyframes; each group's
        messages are kept in ``pending`` in the group's order (its outcomes' order), the frames
        the assembler drops (late, a clashing frame id) never are. `cameras`: each camera's
        counts, summed into ``counts.frames`` as they grow (the progress bar)."""
        assembler, message = RigAssembler(rig, ordered=True), {}
        self.rig = assembler.counts

        def out(groups: list[list[Frame]]) -> Iterator[list[Frame]]:
            for group in groups:
                self.pending.extend(message.pop(id(f)) for f in group)
                yield group

        for frame, bf in pairs:
            self.counts.frames = sum(c.frames for c in cameras)
            if frame.camera_id == 0:
                self.stamps.append(bf.stamp)  # the path: one camera's stamps
            message[id(frame)] = bf  # the assembler holds the frame until it hands it out
            dropped = _dropped(assembler)
            groups = assembler.add(frame)
            if _dropped(assembler) > dropped:  # late or a clashing frame id: never handed out
                message.pop(id(frame))
            yield from out(groups)
        yield from out(assembler.flush())


def _dropped(assembler: RigAssembler) -> int:
    return assembler.counts.frame_id_clash + sum(assembler.counts.late.values())


def global_top1_record(record: LoopRecord, best: Candidate) -> LoopRecord:
    """The record ranking by global similarity alone would give: the top FAISS candidate."""
    return replace(
        record, match_id=best.id, match_stamp=best.stamp, match_frame_id=best.frame_id,
        match_robot=best.robot, match_session=best.session,
        global_similarity=best.global_similarity, pair_score=float("nan"), rank_before=1,
        rank_after=1, accepted=False, reason="global top-1",
    )  # fmt: skip


def drive(
    run: ReplayRun,
    pipe: LoopClosurePipeline,
    frames: Iterator[Frame] | Iterator[list[Frame]],
    batch_size: int,
    writer: LoopBagWriter | None,
    bar: tqdm,
    groups: bool = False,
) -> None:
    """Pipeline outcomes -> records, counts, the decision log, the report's rows, output bag;
    Ctrl-C stops like a read error. `groups`: `frames` are rig keyframes
    (`ReplayRun.rig_groups`)."""
    summary = run.summary
    process = pipe.process_groups if groups else pipe.process_many
    try:
        for outcome in process(frames, batch_size=batch_size):
            bf = run.pending.popleft()
            assert abs(bf.stamp - outcome.stamp) < 1e-9, "outcomes must come in frame order"
            if outcome.keyframe_id is not None:
                summary.keyframes += 1
            elif outcome.represented_by is not None:
                run.represented.append((outcome.stamp, len(pipe.place_map)))
            if writer is not None and bf.cdr is not None:
                writer.write_image(bf.cdr, bf.log_time_ns)
            row = run.log.add(outcome)
            if run.report is not None and row is not None:
                _report(run, row, outcome, bf.rgb)
            if run.pictures is not None:
                run.pictures.keep(outcome, bf.rgb)
            mapped = outcome.keyframe_id is not None or outcome.represented_by is not None
            if outcome.loop is not None and mapped:  # a query of the map (not localization)
                run.global_top1.append(global_top1_record(outcome.loop, outcome.candidates[0]))
            for loop in outcome.reported():  # each accepted loop (one per map), or the best
                run.records.append(loop)
                if loop.accepted:
                    summary.loops += 1
                    key = f"{loop.match_robot}/{loop.match_session}"
                    summary.loops_by_match[key] = summary.loops_by_match.get(key, 0) + 1
                    if writer is not None:
                        writer.write_loop(loop, bf.log_time_ns)
                        picture = run.pictures.draw(outcome, loop, bf.rgb)
                        writer.write_loop_image(loop, picture, bf.log_time_ns)
            bar.update(run.counts.frames - bar.n)
            bar.set_postfix(keyframes=summary.keyframes, loops=summary.loops, refresh=False)
    except KeyboardInterrupt:
        summary.error = f"interrupted after {run.counts.frames} image messages"
        summary.interrupted = True
    except PairVPRError as err:  # the output bag or the map could not be written (disk full)
        summary.error = f"stopped after {run.counts.frames} image messages: {err}"


def _report(run: ReplayRun, row: int, outcome, rgb) -> None:
    """Add a keyframe to the report; one that cannot be written (disk full) stops the report
    with a warning, never the replay: loops and map matter more."""
    try:
        run.report.add(row, outcome, rgb)
    except OutputError as err:
        run.summary.warnings.append(f"the report stopped at keyframe row {row}: {err}")
        run.report = None
