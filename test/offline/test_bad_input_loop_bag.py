"""Bad-input matrix, `--write-bag` (issue 38 #9): a LoopClosure.msg of another build first on
AMENT_PREFIX_PATH is found before the first loop; the bag is written without the typed topic,
with a note naming the definition, and the shared typestore stays clean."""

from __future__ import annotations

import math

import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.messages import loop as loop_messages
from pair_vpr_ros.offline.bags import loop_writer
from pair_vpr_ros.offline.bags.loop_writer import MSG_PATH, SOURCE_MSG, LoopBagWriter

OURS = (SOURCE_MSG / "LoopClosure.msg").read_text()
FOREIGN = {
    "a field missing": OURS.replace("string pose_reason", ""),
    "a field extra": OURS + "\nint32 extra_field\n",
    "a field of another type": OURS.replace("int32 pose_inliers", "string pose_inliers"),
}


def record() -> LoopRecord:
    return LoopRecord(5, 10.0, "cam", 1, 2.0, "cam", pair_score=1.0, global_similarity=0.9,
                      rank_before=1, rank_after=1, accepted=True, tx=math.nan)  # fmt: skip


@pytest.mark.parametrize("case", FOREIGN)
def test_a_foreign_loop_closure_definition(tmp_path, monkeypatch, case):
    # a typestore of its own: the shared one may hold our definition from an earlier test
    monkeypatch.setattr(loop_writer, "jazzy_typestore", lambda: get_typestore(Stores.ROS2_JAZZY))
    definition = tmp_path / "prefix" / MSG_PATH
    definition.parent.mkdir(parents=True)
    definition.write_text(FOREIGN[case])
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "prefix"))
    writer = LoopBagWriter(tmp_path / "out")
    assert writer.typed_note.startswith(
        f"/loop_closure/typed is not written: the definition {definition} does not fit this "
        "version ("
    )
    assert writer.typed_note.endswith(
        "); rebuild pair_vpr_ros_interfaces (docs/interfaces.md) or put this build first on "
        "AMENT_PREFIX_PATH; the other loop-closure topics are written"
    )
    with writer:
        writer.write_loop(record(), 1_000)  # no TypeError at the first loop
    with Reader(tmp_path / "out") as reader:
        topics = sorted(reader.topics)
    assert "/loop_closure/typed" not in topics and "/loop_closure/json" in topics
    assert loop_messages.TYPED_TYPE not in writer._ts.types  # nothing foreign kept
