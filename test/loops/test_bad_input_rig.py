"""Bad rig input (issue 49), each a clear error or a counted skip: a camera with no extrinsic,
two cameras with one frame id, a camera that stops publishing, stamps of one rig keyframe too
far apart, and rig files and settings that are no rig."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.rig import Rig, RigCamera, rig_from_dict
from pair_vpr_ros.loops.rig_frames import RigAssembler, assemble

FRONT = (0.0, 0.0, 1.6, -0.5, 0.5, -0.5, 0.5)
REAR = (-1.0, 0.0, 1.6, 0.5, 0.5, -0.5, -0.5)
RGB = np.zeros((4, 4, 3), np.uint8)


@pytest.mark.parametrize(
    ("cameras", "settings", "message"),
    [
        ((), {}, "a rig needs at least one camera"),
        ((RigCamera("front", FRONT), RigCamera("rear")), {},
         "rig camera 'rear' has no extrinsic: give its camera_to_base"),
        ((RigCamera("front", FRONT, "cam"), RigCamera("rear", REAR, "cam")), {},
         "rig cameras 'front' and 'rear' have one frame id 'cam'"),
        ((RigCamera("front", FRONT), RigCamera("front", REAR)), {},
         "rig camera 'front' is listed twice"),
        ((RigCamera("front/left", FRONT),), {}, "rig camera name 'front/left' must be letters"),
        ((RigCamera("front", (0, 0, 0, 0, 0, 0, 0)),), {}, "camera_to_base has a zero quaternion"),
        ((RigCamera("front", (0, 0, math.nan, 0, 0, 0, 1)),), {}, "must be 7 finite numbers"),
        ((RigCamera("front", FRONT),), {"stamp_tolerance": 2.0}, "stamp_tolerance 2.0 must be"),
        ((RigCamera("front", FRONT),), {"stamp_tolerance": math.nan}, "stamp_tolerance nan"),
        ((RigCamera("front", FRONT),), {"max_delay": -1.0}, "rig max_delay -1.0 must be"),
        ((RigCamera("front", FRONT),), {"base_frame": ""}, "rig base_frame '' must be a frame"),
    ],
)  # fmt: skip
def test_a_bad_rig_is_refused_with_what_to_do(cameras, settings, message) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        Rig(cameras, **settings)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ([], "rig.yaml: a rig file needs a list 'cameras'"),
        ({"cameras": "front"}, "rig.yaml: a rig file needs a list 'cameras'"),
        ({"cameras": [{"topic": "/a"}]}, "rig.yaml: camera 0 must be a mapping with a 'name'"),
        ({"cameras": [{"name": "front", "topic": "/a"}]},
         "rig.yaml: camera 'front' has unknown keys ['topic']"),
        ({"cameras": [{"name": "front", "camera_to_base": [1, 2, 3]}]},
         "rig.yaml: camera 'front' camera_to_base must be 7 finite numbers"),
        ({"cameras": [{"name": "front", "camera_to_base": "up"}]},
         "rig.yaml: camera 'front' camera_to_base must be 7 numbers"),
        ({"cameras": [{"name": "a", "camera_to_base": list(FRONT)}], "tolerance": 1},
         "rig.yaml: unknown keys ['tolerance']"),
        ({"cameras": [{"name": "a", "camera_to_base": list(FRONT)}], "max_delay": "soon"},
         "rig.yaml: stamp_tolerance and max_delay are seconds"),
        ({"cameras": [{"name": "a", "camera_to_base": list(FRONT)}, {"name": "b"}]},
         "rig.yaml: rig camera 'b' has no extrinsic"),
    ],
)  # fmt: skip
def test_a_bad_rig_file_names_the_file_and_the_problem(data, message) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        rig_from_dict(data, "rig.yaml")


RIG = Rig((RigCamera("front", FRONT), RigCamera("rear", REAR)))


def _frames(stamps: dict[int, list[float]], frame_ids=("front", "rear")) -> list[Frame]:
    out = [Frame(t, RGB, frame_ids[cam], camera_id=cam) for cam, ts in stamps.items() for t in ts]
    return sorted(out, key=lambda f: (f.stamp, f.camera_id))


def test_a_camera_that_stops_publishing_is_counted_and_never_blocks_the_others() -> None:
    frames = _frames({0: [0.1 * i for i in range(10)], 1: [0.1 * i for i in range(4)]})
    asm = RigAssembler(RIG, ordered=True)
    groups = [g for f in frames for g in asm.add(f)] + asm.flush()
    assert [len(g) for g in groups] == [2] * 4 + [1] * 6  # every instant, with what came
    assert asm.counts.missing == {"rear": 6} and asm.counts.incomplete == 6
    assert "rig keyframes without a camera: rear (6) of 10" in asm.counts.warnings()[0]


def test_stamps_too_far_apart_are_counted_with_the_gap_and_nothing_is_lost() -> None:
    frames = _frames({0: [0.1 * i for i in range(6)], 1: [0.1 * i + 0.03 for i in range(6)]})
    groups = list(assemble(frames, RIG))
    assert sum(len(g) for g in groups) == 12 and all(len(g) == 1 for g in groups)
    asm = RigAssembler(RIG, ordered=True)
    for f in frames:
        asm.add(f)
    asm.flush()
    assert asm.counts.apart["rear"] >= 3 and asm.counts.max_apart_ms == pytest.approx(30.0)
    assert "raise stamp_tolerance or synchronise" in asm.counts.warnings()[0]


def test_two_cameras_with_one_frame_id_are_counted_and_the_second_is_dropped() -> None:
    frames = _frames({0: [0.0, 0.1], 1: [0.0, 0.1]}, frame_ids=("cam", "cam"))
    asm = RigAssembler(RIG, ordered=True)
    groups = [g for f in frames for g in asm.add(f)] + asm.flush()
    assert [[f.camera_id for f in g] for g in groups] == [[0], [0]]
    assert asm.counts.frame_id_clash == 2
    assert "2 frames dropped: their frame_id is another camera's" in asm.counts.warnings()[-1]
