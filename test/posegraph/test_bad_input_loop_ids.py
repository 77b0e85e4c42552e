"""Bad-input matrix, issue 38: camera frame ids holding ``@``, loops with an absurd finite
translation or a damaged identity, and loops.json records whose covariance has the wrong
length. Each is carried whole or is a counted skip under its reason; none stops the graph."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
from loop_records import posed_record
from rosbags.typesys import Stores, get_typestore
from test_posegraph import loop, loop_covariance

from pair_vpr_ros.messages import factor as lf
from pair_vpr_ros.messages.loop import record_dict
from pair_vpr_ros.offline.report.loop_io import read_loops
from pair_vpr_ros.posegraph.config import PoseGraphConfig
from pair_vpr_ros.posegraph.graph import PoseGraph
from pair_vpr_ros.posegraph.transforms import planar_pose7

TS = get_typestore(Stores.ROS2_JAZZY)
FRAMES = ["cam@front", "cam@a@b", "@", "a@@", "cam@x@r1@s1", "cam@@x", "cam@1r@s"]
WITHIN = dict(query_robot="r1", query_session="s2", match_robot="r1", match_session="s2")
BETWEEN = dict(query_robot="r1", query_session="s2", match_robot="r0", match_session="s1")


@pytest.mark.parametrize("frame", FRAMES)
@pytest.mark.parametrize("who", [{}, WITHIN, BETWEEN], ids=["old", "within", "between"])
def test_any_camera_frame_id_round_trips(frame, who):
    """An ``@`` in a camera frame_id never moves a loop to another robot-session."""
    factor = lf.factor_from_record(posed_record(query_frame_id=frame, match_frame_id="m@" + frame,
                                                **who))  # fmt: skip
    msg = lf.factor_msg(factor, TS.types)
    back = lf.factor_from_msg(TS.deserialize_cdr(TS.serialize_cdr(msg, lf.FACTOR_TYPE),
                                                 lf.FACTOR_TYPE))  # fmt: skip
    # within one robot-session the identity is left to the topic it came on (as before)
    want = factor if who is BETWEEN else replace(factor, **dict.fromkeys(WITHIN, ""))
    assert back == want
    assert (back.query_frame_id, back.match_frame_id) == (frame, "m@" + frame)


def test_untagging_takes_only_valid_names():
    assert lf.untag_frame("cam@r1@s1") == ("cam", "r1", "s1")
    assert lf.untag_frame("cam@x@@") == ("cam@x", "", "")
    assert lf.untag_frame("cam@1r@s1") == ("cam@1r@s1", "", "")  # '1r' is no robot id
    assert lf.untag_frame("cam@r.1@s1") == ("cam@r.1@s1", "", "")
    assert lf.untag_frame("cam") == ("cam", "", "")


def graph_with_odometry() -> PoseGraph:
    graph = PoseGraph(PoseGraphConfig(stamp_tolerance_s=0.2))
    for i in range(20):
        graph.add_odometry(10.0 + i, planar_pose7(2.0 * i, 0, 0))
    return graph


LOOP_CASES = {
    "translation 1e9 m": (
        dict(translation=(1e9, 0.0, 0.0)),
        "transform: translation beyond 1e+05 m (1e+09 m)",
        "loop: transform: translation beyond 1e+05 m",
    ),
    "translation 2e5 m": (
        dict(translation=(0.0, -2e5, 0.0)),
        "transform: translation beyond 1e+05 m (2e+05 m)",
        "loop: transform: translation beyond 1e+05 m",
    ),
    "robot id '..'": (
        dict(query_robot="..", query_session="s"),
        "query_robot is no valid robot or session id ('..')",
        "loop: query_robot is no valid robot or session id",
    ),
    "session id 'a/b'": (
        dict(match_robot="r", match_session="a/b"),
        "match_session is no valid robot or session id ('a/b')",
        "loop: match_session is no valid robot or session id",
    ),
}


@pytest.mark.parametrize("case", LOOP_CASES)
def test_damaged_loops_are_counted_skips_and_the_graph_goes_on(case):
    changes, reason, key = LOOP_CASES[case]
    graph = graph_with_odometry()
    good = loop(20.0, 12.0, (0, 0, 0, 0, 0, 0, 1), loop_covariance())
    assert graph.add_loop(replace(good, **changes)) == reason
    assert graph.add_loop(good) == "added"
    graph.finish()  # GTSAM never sees the damaged loop: no "Indeterminate linear system"
    assert graph.counts.skipped == {key: 1} and graph.counts.loops_added == 1
    assert graph.optimised_poses().shape == (20, 7)


@pytest.mark.parametrize("values", [35, 6, 0])
def test_a_covariance_of_the_wrong_length_is_named(tmp_path, values):
    records = [
        record_dict(posed_record()),
        {**record_dict(posed_record()), "covariance": [0.1] * values},
    ]
    (tmp_path / "loops.json").write_text(json.dumps(records))
    source = read_loops(tmp_path / "loops.json")
    assert (source.accepted, len(source.factors)) == (2, 1)
    assert dict(source.left_out) == {f"covariance of {values} values, not 36": 1}
