"""Bad-input matrix, poses: a NaN or infinite value in any pose field or the stamp is refused and
counted by the pose track (node and replay alike), so no keyframe ever carries it (issue 13 #5:
one such pose used to abort a replay with nothing written)."""

from __future__ import annotations

import math

import pytest

from pair_vpr_ros.place_map import KeyframeMeta, PlaceMap
from pair_vpr_ros.types import PoseTrack

FIELDS = ("x", "y", "z", "qx", "qy", "qz", "qw")
GOOD = (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)
BAD_VALUES = {"nan": math.nan, "+inf": math.inf, "-inf": -math.inf}


def _with(field: int, value: float) -> tuple[float, ...]:
    return GOOD[:field] + (value,) + GOOD[field + 1 :]


CASES = [
    (f"{FIELDS[i]} {name}", 10.0, _with(i, value))
    for i in range(7)
    for name, value in BAD_VALUES.items()
] + [(f"stamp {name}", value, GOOD) for name, value in BAD_VALUES.items()]


@pytest.mark.parametrize(("case", "stamp", "pose"), CASES, ids=[c[0] for c in CASES])
def test_non_finite_pose_is_refused_and_counted(case, stamp, pose) -> None:
    track = PoseTrack()
    assert track.add(9.0, GOOD)
    assert not track.add(stamp, pose)
    assert (len(track), track.rejected) == (1, 1)
    assert track.first_rejected == stamp or (
        math.isnan(stamp) and math.isnan(track.first_rejected)
    )
    assert track.nearest(10.0, 0.5) is None  # the frame at 10 s gets no pose, not a bad one
    assert track.nearest(10.0, 1.0) == GOOD
    assert track.add(11.0, GOOD) and track.rejected == 1


def test_the_map_would_refuse_such_a_pose(tmp_path) -> None:
    """Why the track must filter: a keyframe with a non-finite pose is a MapError (the replay
    used to stop there)."""
    from pair_vpr_ros.errors import MapError

    with PlaceMap(4, (2, 2)) as m, pytest.raises(MapError, match="7 finite numbers"):
        m.add([1, 0, 0, 0], [[0, 0], [0, 0]], KeyframeMeta(stamp=1.0, pose=_with(0, math.nan)))


def test_build_map_reports_the_bad_poses_it_skipped(tiny_model, tmp_path) -> None:
    """Issue 25 #5: `build_map` (the node's ~/build_map) read a bag's poses and dropped the bad
    ones without a word; its result line (map_info, the node's log) now names them."""
    from bag_fixtures import synthetic_images, write_rosbag2

    from pair_vpr_ros.loops.detector import DetectorConfig
    from pair_vpr_ros.offline.replay.build_map import build_map

    images = [(10.0 + i, rgb) for i, rgb in enumerate(synthetic_images(3))]
    poses = [(10.0, (0.0, 2.0, 0.0)), (11.0, (math.nan, 2.0, 0.0)), (12.0, (2.0, 2.0, 0.0))]
    bag = write_rosbag2(tmp_path / "bag", images, poses)
    pipe, result = build_map(tiny_model, DetectorConfig(), bag)
    pipe.close()
    assert result.counts.bad_poses == 1
    assert result.line().endswith(
        "; 1 poses of /odom hold NaN or infinite values and were skipped (the first at stamp "
        "11.000 s); frames near them have no pose"
    )
    assert result.line().startswith(f"{result.keyframes} keyframes from 3 images of {bag} (0 ")
