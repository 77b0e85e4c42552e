"""A replay of several cameras (issue 49): the rig from ``--rig FILE`` or repeated ``--topic``,
every camera's frames merged into rig keyframes for the one pipeline, and what each camera gave
folded into the replay's counts and summary (`ReplaySummary.rig`)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader

from pair_vpr_ros.errors import UsageError
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.rig import Rig
from pair_vpr_ros.offline.bags import rig as bag_rig
from pair_vpr_ros.offline.bags.sources import FrameCounts
from pair_vpr_ros.offline.replay.drive import ReplayRun

PER_CAMERA = ("depth_topic", "camera_info_topic", "right_topic", "right_camera_info_topic")


def camera_options(args: Any) -> dict[str, Any]:
    """``ReplayOptions``' topic, topics and rig_file from the command line (``--topic``
    repeated, ``--rig``); UsageError for flags that do not go together."""
    topics = args.topic or []
    if args.rig and topics:
        raise UsageError("give --rig FILE or --topic, not both: the rig file names the topics")
    given = [f"--{n.replace('_', '-')}" for n in PER_CAMERA if getattr(args, n)]
    if (args.rig or len(topics) > 1) and given:
        raise UsageError(f"{', '.join(given)} with several cameras: give each camera's topics in "
                         "a rig file (--rig)")  # fmt: skip
    several = len(topics) > 1
    return dict(topic=None if several else (topics or [None])[0],
                topics=tuple(topics) if several else (), rig_file=args.rig)  # fmt: skip


def open_rig(reader: AnyReader, options: Any) -> tuple[Rig | None, list[str]]:
    """The replay's rig (None: one camera, as before) and notes on how it was made."""
    if options.rig_file:
        cams, settings = bag_rig.read_rig_file(options.rig_file)
        where = f"rig file {options.rig_file}"
    elif len(options.topics) > 1:
        cams, settings = bag_rig.rig_from_topics(reader, list(options.topics)), {}
        where = "--topic " + " --topic ".join(options.topics)
    else:
        return None, []
    rig, notes = bag_rig.resolve_rig(reader, cams, settings, where)
    described = ", ".join(f"{c.name} ({c.image_topic}; camera_info {c.camera_info_topic or 'none'}"
                          f", depth {c.depth_topic or 'none'})" for c in rig.cameras)  # fmt: skip
    notes.insert(0, f"rig of {len(rig.cameras)} cameras from {where}: {described}; rig "
                 f"keyframes within {rig.stamp_tolerance * 1e3:g} ms, loops in "
                 f"{rig.base_frame}")  # fmt: skip
    return rig, notes


class RigSource:
    """The rig keyframes of a bag, and each camera's counts."""

    def __init__(self, reader: AnyReader, rig: Rig, poses: Any, options: Any, bag: str) -> None:
        self.rig, self.cameras = rig, [FrameCounts() for _ in rig.cameras]
        self.total = sum(reader.topics[c.image_topic].msgcount for c in rig.cameras)
        if options.max_frames is not None:
            self.total = min(self.total, options.max_frames * len(rig.cameras))
        self._streams = [
            bag_rig.camera_frames(reader, rig, k, poses, options, self.cameras[k], Path(bag).name)
            for k in range(len(rig.cameras))
        ]

    def groups(self, run: ReplayRun) -> Iterator[list[Frame]]:
        return run.rig_groups(bag_rig.merged(self._streams), self.rig, self.cameras)

    def fold(self, run: ReplayRun) -> None:
        """Each camera's counts into the run's, the rig's summary into ``summary.rig``; called
        after the drive, also after a failure."""
        total, summary = run.counts, run.summary
        for counts in self.cameras:
            total.skipped += counts.skipped
            total.reasons.update(counts.reasons)
            total.geometry_skips.update(counts.geometry_skips)
            total.backwards += counts.backwards
            total.repeated += counts.repeated
            total.error = total.error or counts.error
        total.frames = sum(c.frames for c in self.cameras)
        rig_counts = run.rig.to_dict() if run.rig is not None else {}
        summary.warnings += run.rig.warnings() if run.rig is not None else []
        cams = [dict(name=c.name, image_topic=c.image_topic, frame_id=c.frame_id,
                     camera_to_base=list(c.camera_to_base or ()), frames=n.frames)
                for c, n in zip(self.rig.cameras, self.cameras, strict=True)]  # fmt: skip
        summary.rig = {
            "cameras": cams,
            "stamp_tolerance": self.rig.stamp_tolerance,
            "base_frame": self.rig.base_frame,
            **rig_counts,
        }
