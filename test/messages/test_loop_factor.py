"""messages.factor: a loop's between-factor and its nav_msgs/Odometry encoding, round trips."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from loop_records import COV, posed_record
from rosbags.typesys import Stores, get_typestore

from pair_vpr_ros.messages import factor as lf

TS = get_typestore(Stores.ROS2_JAZZY)


def test_factor_from_record_needs_an_accepted_loop_with_a_pose():
    factor = lf.factor_from_record(posed_record())
    assert factor is not None and factor.metric and factor.inliers == 88
    assert (factor.query_id, factor.match_id) == (40, 3)
    assert factor.translation == (0.5, -0.1, 2.0) and factor.covariance == COV
    assert lf.factor_from_record(posed_record(accepted=False)) is None
    assert lf.factor_from_record(posed_record(pose_status="", covariance=())) is None
    scale_free = lf.factor_from_record(posed_record(pose_status="scale-free"))
    assert scale_free is not None and not scale_free.metric


def test_factor_from_a_json_dict_equals_the_one_from_the_record():
    from pair_vpr_ros.messages.loop import record_dict

    record = posed_record()
    assert lf.factor_from_record(record_dict(record)) == lf.factor_from_record(record)


WHO = dict(query_robot="r1", query_session="s2", match_robot="r0", match_session="s1")


def test_factor_carries_both_sides_identity_and_old_records_read_as_empty():
    from pair_vpr_ros.messages.loop import record_dict

    factor = lf.factor_from_record(posed_record(**WHO))
    assert {k: getattr(factor, k) for k in WHO} == WHO
    assert lf.factor_from_record(record_dict(posed_record(**WHO))) == factor
    old = {k: v for k, v in record_dict(posed_record(**WHO)).items() if k not in WHO}
    assert {k: getattr(lf.factor_from_record(old), k) for k in WHO} == dict.fromkeys(WHO, "")


def test_odometry_encoding_stays_as_it_was_within_one_robot_session():
    """A loop within one robot-session: the old encoding, identity left to the topic it came
    on (posegraph_node reads each robot's loops on its own topic)."""
    within = dict(query_robot="r1", query_session="s2", match_robot="r1", match_session="s2")
    factor = lf.factor_from_record(posed_record(**within))
    msg = lf.factor_msg(factor, TS.types)
    back = TS.deserialize_cdr(TS.serialize_cdr(msg, lf.FACTOR_TYPE), lf.FACTOR_TYPE)
    assert back.header.frame_id == "cam_m" and back.child_frame_id == "cam_q"
    assert lf.factor_from_msg(back) == replace(factor, **dict.fromkeys(within, ""))
    # between two robot-sessions (new with issue 22) both frame ids carry their side
    between = lf.factor_from_record(posed_record(**WHO))
    msg = lf.factor_msg(between, TS.types)
    assert (msg.child_frame_id, msg.header.frame_id) == ("cam_q@r1@s2", "cam_m@r0@s1")
    assert lf.factor_from_msg(msg) == between


@pytest.mark.parametrize("status", ["metric", "scale-free", "metric-odometry"])
def test_odometry_message_round_trip_through_cdr(status):
    factor = lf.factor_from_record(posed_record(pose_status=status))
    msg = lf.factor_msg(factor, TS.types)
    assert msg.__msgtype__ == lf.FACTOR_TYPE
    back = TS.deserialize_cdr(TS.serialize_cdr(msg, lf.FACTOR_TYPE), lf.FACTOR_TYPE)
    assert (back.header.stamp.sec, back.header.stamp.nanosec) == (1700000012, 250000000)
    assert (back.twist.twist.linear.x, back.twist.twist.linear.y) == (1700000001.0, 5e8)
    assert back.header.frame_id == "cam_m" and back.child_frame_id == "cam_q"
    assert back.twist.twist.linear.z == {"metric": 1.0, "scale-free": 2.0}.get(status, 3.0)
    assert (factor.metric, factor.scale_from_odometry) == (
        status != "scale-free",
        status == "metric-odometry",
    )
    assert back.twist.covariance.tolist() == [0.0] * 36
    assert lf.factor_from_msg(back) == factor


def test_a_message_that_is_not_a_factor_is_refused():
    msg = lf.factor_msg(lf.factor_from_record(posed_record()), TS.types)
    msg.twist.twist.linear.z = 0.0  # e.g. a real odometry message on the wrong topic
    with pytest.raises(ValueError, match="not a loop_closure/factor message: .* status code 0.0"):
        lf.factor_from_msg(msg)


def test_matrix_maps_query_points_into_the_match_frame():
    factor = lf.factor_from_record(posed_record())
    t = factor.matrix()
    expected_r = cv2.Rodrigues(np.array([0.0, 0.4, 0.0]))[0]  # 0.4 rad about y
    np.testing.assert_allclose(t[:3, :3], expected_r, atol=1e-12)
    np.testing.assert_allclose(t @ [0, 0, 0, 1], [0.5, -0.1, 2.0, 1.0])


def test_gtsam_covariance_is_the_right_perturbation_in_the_query_frame():
    factor = lf.factor_from_record(posed_record())
    r, t = factor.matrix()[:3, :3], factor.matrix()[:3, 3]
    rng = np.random.default_rng(0)
    a = np.zeros((6, 6))  # numerical Jacobian d xi / d (d_t, d_rot) at 0
    eps = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        r_true = cv2.Rodrigues(d[3:])[0] @ r
        t_true = t + d[:3]
        m = r.T @ r_true  # rotation error in the query frame; its Log to first order:
        omega = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) / 2
        v = r.T @ (t_true - t)
        a[:, k] = np.r_[omega, v] / eps
    cov = np.asarray(COV).reshape(6, 6) + 0.001 * np.diag(rng.random(6))
    factor = lf.LoopFactor(**{**factor.__dict__, "covariance": tuple(cov.ravel())})
    np.testing.assert_allclose(factor.gtsam_covariance(), a @ cov @ a.T, rtol=1e-5, atol=1e-12)


def test_factor_msg_works_on_plain_constructors():
    """Any classes taking the fields as keywords (rclpy's do) build the same message."""
    types = {name: SimpleNamespace for name in lf.FACTOR_MSG_TYPES}
    msg = lf.factor_msg(lf.factor_from_record(posed_record()), types)
    assert lf.factor_from_msg(msg) == lf.factor_from_record(posed_record())


def test_robot_and_session_of_a_loop_between_two_ride_in_the_frame_ids():
    from dataclasses import asdict, replace

    plain = lf.factor_from_record(posed_record())
    assert (plain.query_robot, plain.query_session, plain.match_robot, plain.match_session) == (
        "", "", "", ""
    )  # fmt: skip
    factor = replace(plain, query_robot="b", query_session="day1", match_robot="a",
                     match_session="20261125T120000Z")  # fmt: skip
    msg = lf.factor_msg(factor, TS.types)
    assert msg.child_frame_id == "cam_q@b@day1"
    assert msg.header.frame_id == "cam_m@a@20261125T120000Z"
    back = TS.deserialize_cdr(TS.serialize_cdr(msg, lf.FACTOR_TYPE), lf.FACTOR_TYPE)
    assert lf.factor_from_msg(back) == factor
    # within one robot-session: the old encoding, the identity left to the topic it came on
    within = replace(plain, query_robot="a", query_session="s", match_robot="a", match_session="s")
    msg = lf.factor_msg(within, TS.types)
    assert (msg.child_frame_id, msg.header.frame_id) == ("cam_q", "cam_m")
    assert lf.factor_from_msg(msg) == plain
    assert lf.untag_frame("a@b") == ("a@b", "", "")  # not a tag: the frame id as it is
    record = {**asdict(posed_record()), "query_robot": "b", "match_session": None}
    assert lf.factor_from_record(record).query_robot == "b"  # JSON null: ""
    assert lf.factor_from_record(record).match_session == ""
