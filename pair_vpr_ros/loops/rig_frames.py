"""Rig keyframes: the frames of a rig's cameras taken at one instant, grouped for the pipeline.

`RigAssembler` takes frames of every camera (`Frame.camera_id` = the camera's index in the rig)
and hands out groups, oldest first: the frames whose stamps lie within `Rig.stamp_tolerance` of
the group's first frame, one per camera. A group goes out as soon as every camera is in it;
one that lacks a camera goes out without it, counted (`RigCounts.missing`), never waiting
beyond:

* ``ordered`` input (the replay: every camera's frames merged by stamp): once a frame stamped
  past the group's tolerance arrives, nothing can join it any more;
* otherwise (the node: each camera's callback on its own), ``max_delay`` s of wall clock after
  the group's first frame came (`poll` asks), or when a camera's next frame arrives.

A frame that comes after its group went out is dropped and counted (`late`); one whose nearest
group was too far in time starts a group of its own, and a group that lacks a camera whose
frame came within ``APART_S`` of it is counted as ``apart`` with the gap (stamps of one rig
keyframe too far apart: raise ``stamp_tolerance`` or synchronise the cameras) rather than as
missing when that frame was nearer than half the camera's frame period. A single camera's
groups are single frames (`LoopClosurePipeline.process_many`).
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.rig import Rig, check_frame_ids

APART_S = 0.5  # a camera's frame this close to a group it missed: stamps apart, not missing


@dataclass
class RigCounts:
    """What the assembler did: rig keyframes handed out, those without every camera, and per
    camera name the keyframes it missed, its frames that came too late or too far apart."""

    keyframes: int = 0
    incomplete: int = 0
    missing: Counter[str] = field(default_factory=Counter)
    late: Counter[str] = field(default_factory=Counter)
    apart: Counter[str] = field(default_factory=Counter)
    max_apart_ms: float = 0.0  # the largest gap of an `apart` camera to its group
    frame_id_clash: int = 0  # frames dropped: their frame id is another camera's

    def to_dict(self) -> dict:
        return {"keyframes": self.keyframes, "incomplete": self.incomplete,
                "missing": dict(self.missing), "late": dict(self.late),
                "apart": dict(self.apart), "max_apart_ms": round(self.max_apart_ms, 3),
                "frame_id_clash": self.frame_id_clash}  # fmt: skip

    def warnings(self) -> list[str]:
        """What to tell the user ([] when every rig keyframe had every camera)."""
        out = []
        if self.apart:
            names = ", ".join(f"{k} ({n})" for k, n in sorted(self.apart.items()))
            out.append(f"rig keyframes whose camera frames were stamped too far apart: {names}, "
                       f"up to {self.max_apart_ms:.1f} ms: raise stamp_tolerance or "
                       "synchronise the cameras' triggers")  # fmt: skip
        gone = {k: n for k, n in self.missing.items() if n}
        if gone:
            names = ", ".join(f"{k} ({n})" for k, n in sorted(gone.items()))
            out.append(f"rig keyframes without a camera: {names} of {self.keyframes} (a camera "
                       "that stopped publishing or drops frames; the others went on)")  # fmt: skip
        if self.late:
            names = ", ".join(f"{k} ({n})" for k, n in sorted(self.late.items()))
            out.append(f"camera frames that came after their rig keyframe was processed and were "
                       f"dropped: {names} (raise rig max_delay)")  # fmt: skip
        if self.frame_id_clash:
            out.append(f"{self.frame_id_clash} frames dropped: their frame_id is another "
                       "camera's (each camera needs its own frame_id)")  # fmt: skip
        return out


@dataclass
class _Group:
    stamp: float  # the first frame's
    since: float  # wall clock when it was opened
    frames: dict[int, Frame] = field(default_factory=dict)


class RigAssembler:
    """Frames of a rig's cameras -> rig keyframes (lists of frames, camera order), oldest
    first. `clock`: wall-clock seconds (tests pass their own). Not thread-safe."""

    def __init__(self, rig: Rig, ordered: bool = False,
                 clock: Callable[[], float] = time.monotonic) -> None:  # fmt: skip
        self.rig, self.ordered, self.clock = rig, ordered, clock
        self.counts = RigCounts()
        self._open: list[_Group] = []
        self._last_out: float | None = None  # stamp of the newest group handed out
        self._recent: dict[int, list[float]] = {}  # camera -> its last few frame stamps
        self._frame_ids: dict[int, str] = {}

    def add(self, frame: Frame) -> list[list[Frame]]:
        """Take one frame; -> the rig keyframes now complete (or given up on), oldest first."""
        cam, tol = frame.camera_id, self.rig.stamp_tolerance
        if not self._frame_id_ok(cam, frame.frame_id):
            self.counts.frame_id_clash += 1
            return self._ready()
        self._recent.setdefault(cam, []).append(frame.stamp)
        del self._recent[cam][:-8]
        if self._last_out is not None and frame.stamp <= self._last_out + tol:
            self.counts.late[self.rig.name(cam)] += 1  # its group is gone: never block on it
            return self._ready()
        near = [g for g in self._open if abs(g.stamp - frame.stamp) <= tol and cam not in g.frames]
        if near:
            min(near, key=lambda g: abs(g.stamp - frame.stamp)).frames[cam] = frame
        else:
            self._open.append(_Group(frame.stamp, self.clock(), {cam: frame}))
            self._open.sort(key=lambda g: g.stamp)
        return self._ready(frame.stamp if self.ordered else None)

    def poll(self) -> list[list[Frame]]:
        """The rig keyframes whose wait (``max_delay``) is over (the node's timer)."""
        return self._ready()

    def flush(self) -> list[list[Frame]]:
        """Every group still open, oldest first (the end of a bag)."""
        out = [self._close(g, [i for i in range(len(self.rig.cameras)) if i not in g.frames])
               for g in self._open]  # fmt: skip
        self._open.clear()
        return out

    def _ready(self, newest: float | None = None) -> list[list[Frame]]:
        """Close, oldest first, the groups that are complete or cannot grow any more."""
        out, now, tol = [], self.clock(), self.rig.stamp_tolerance
        while self._open:
            g = self._open[0]
            missing = [i for i in range(len(self.rig.cameras)) if i not in g.frames]
            # ordered input past the group, or each missing camera sent a later frame already
            passed = newest is not None and newest > g.stamp + tol
            moved_on = all(self._recent.get(m, [-math.inf])[-1] > g.stamp + tol for m in missing)
            waited = not self.ordered and now - g.since >= self.rig.max_delay
            if not (passed or moved_on or waited):
                break
            out.append(self._close(self._open.pop(0), missing))
        return out

    def _close(self, g: _Group, missing: list[int]) -> list[Frame]:
        self.counts.keyframes += 1
        self._last_out = g.stamp if self._last_out is None else max(self._last_out, g.stamp)
        self.counts.incomplete += bool(missing)
        for cam in missing:
            name, stamps = self.rig.name(cam), self._recent.get(cam, [])
            gap = min((abs(s - g.stamp) for s in stamps), default=math.inf)
            # nearer than half its own frame period: that frame was meant for this instant
            period = float(np.median(np.diff(stamps))) if len(stamps) > 2 else 0.0  # unknown
            if gap < min(period / 2, APART_S):
                self.counts.apart[name] += 1
                self.counts.max_apart_ms = max(self.counts.max_apart_ms, gap * 1e3)
            else:
                self.counts.missing[name] += 1
        return [g.frames[i] for i in sorted(g.frames)]

    def _frame_id_ok(self, cam: int, frame_id: str) -> bool:
        """The first frame id of each camera is its own; another camera's is refused."""
        if not frame_id:
            return True
        if cam not in self._frame_ids:
            try:
                check_frame_ids({**{str(c): f for c, f in self._frame_ids.items()},
                                 str(cam): frame_id})  # fmt: skip
            except Exception:  # noqa: BLE001 - a clash: the caller counts it
                return False
            self._frame_ids[cam] = frame_id
        return True


def assemble(frames: Iterable[Frame], rig: Rig) -> Iterator[list[Frame]]:
    """Frames of every camera merged by stamp (the replay) -> rig keyframes, oldest first."""
    assembler = RigAssembler(rig, ordered=True)
    for frame in frames:
        yield from assembler.add(frame)
    yield from assembler.flush()


def any_new(frames: list[Frame], desc: np.ndarray, last: Mapping[int, np.ndarray],
            detector: Any) -> bool:  # fmt: skip
    """Is a group a keyframe: does any frame's descriptor (`desc` [>= len(frames), D], in
    order) differ from its camera's last keyframe's (`last`; `detector.is_new_keyframe`)?"""
    sims = [None if (d := last.get(f.camera_id)) is None else float(desc[i] @ d)
            for i, f in enumerate(frames)]  # fmt: skip
    return any(detector.is_new_keyframe(s) for s in sims)
