"""What a replay's summary says about runs that are honest but easy to misread: every keyframe
inside the exclusion window (no loop is possible), the shipped demo model on real images."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

from pair_vpr_ros.geometry.camera_notes import demo_model_note


def exclusion_notes(keyframes: Sequence[Any], evaluation: Any) -> list[str]:
    """When no keyframe has a true match because all of them lie within the evaluation's
    exclusion_s of each other (`keyframes`: ``KeyframeInfo`` with ``stamp``): say so."""
    exclusion_s = evaluation.exclusion_s
    if evaluation.positives or len(keyframes) < 2:
        return []
    stamps = [k.stamp for k in keyframes]
    span = max(stamps) - min(stamps)
    if span >= exclusion_s:
        return []
    return [f"all {len(keyframes)} keyframes lie within the exclusion window: the bag spans "
            f"{span:.1f} s of keyframes, less than exclude_recent_s = {exclusion_s:g} s, so no "
            "pair may be a loop and '0 keyframes with a true match' says nothing about the "
            "detector; lower exclude_recent_s (--params-file) for a short bag"]  # fmt: skip


def note_demo_model(frames: Iterator[Any], summary: Any) -> Iterator[Any]:
    """Pass `frames` on; at the first one, add the demo-model note (`camera_notes`) to
    `summary.warnings` when the shipped demo model (`summary.model`) runs on other images."""
    first = True
    for frame in frames:
        if first:
            first = False
            note = demo_model_note(summary.model, frame.rgb)
            if note:
                summary.warnings.append(note)
        yield frame
