"""One loop closure as a pose-graph between-factor, and its ``nav_msgs/Odometry`` encoding.

No standard message holds two stamps, two frame ids, a transform and a 6x6 covariance, so the
``loop_closure/factor`` topic uses ``nav_msgs/Odometry`` (a pose of ``child_frame_id`` in
``header.frame_id`` with a covariance, as the factor is) and puts the second stamp and some
bookkeeping into the otherwise unused twist:

==============================  ==================================================================
field                           content
==============================  ==================================================================
header.stamp                    query keyframe's image stamp (t_current)
header.frame_id                 match keyframe's image frame_id (the reference frame)
child_frame_id                  query keyframe's image frame_id
pose.pose.position              translation of T_match_query: the query camera's position in the
                                match camera's optical frame, m (scale-free: a unit vector)
pose.pose.orientation           rotation of T_match_query (query camera axes in the match frame)
pose.covariance                 6x6 row-major, order (x, y, z, rx, ry, rz), errors expressed in the
                                match camera frame (see ``LoopFactor.gtsam_covariance``)
twist.twist.linear.x / .y       match keyframe's image stamp (t_previous): sec / nanosec
twist.twist.linear.z            1.0 metric (depth), 2.0 scale-free (translation variance 1e6 m^2),
                                3.0 metric, monocular, scale from a short odometry baseline
twist.twist.angular.x           inliers of the pose fit
twist.twist.angular.y / .z      query / match keyframe ids in the place map
twist.covariance                [0] / [1]: query / match keyframe's rig camera (0: the only
                                camera); the rest zeros
==============================  ==================================================================

A consumer adds ``BetweenFactor(X(match), X(query), T_match_query, covariance)`` after moving it
from the camera frame to its body frame (camera extrinsics).

A rig of several cameras (``loops/rig.py``, issue 49) gives its loops in the robot's base frame
instead: both frame ids are the base frame (``LoopRecord.pose_frame``), the pose is
``T_base_a T_a_b T_b_base`` between the two keyframes' base poses (camera a took the match,
camera b the query), the covariance carried through, and the twist's covariance names the two
cameras. A pose graph over base poses takes it as it is (no camera extrinsics to apply).

Robot and session of both keyframes (``LoopFactor.query_robot`` ... ``match_session``, issue 22):
a loop within one robot-session keeps the encoding above unchanged (its frame ids as they are;
decoded, all four are "": the robot-session of the topic it came on, as posegraph_node reads
it). A loop *between* two robot-sessions, new with issue 22, tags both frame ids
``<frame_id>@<robot>@<session>`` (``tag_frame``; frame and robot ids are ROS names, which
cannot hold ``@``), so the pose graph can key it by both trajectories. The JSON, CSV,
``loops.json`` and the detail topic carry all four as text, and the typed ``LoopClosure``
message (issue 22 part 2) as string fields.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from pair_vpr_ros.geometry.covariance import SCALE_FREE_VARIANCE  # noqa: F401 (consumers)
from pair_vpr_ros.geometry.rotations import quaternion_matrix
from pair_vpr_ros.identity import name_problem
from pair_vpr_ros.types import split_stamp

FACTOR_TOPIC = "loop_closure/factor"
FACTOR_TYPE = "nav_msgs/msg/Odometry"
POSE_MSG_TYPES = (  # a stamped header and a pose with covariance: what both loop messages hold
    "builtin_interfaces/msg/Time",
    "std_msgs/msg/Header",
    "geometry_msgs/msg/Point",
    "geometry_msgs/msg/Quaternion",
    "geometry_msgs/msg/Pose",
    "geometry_msgs/msg/PoseWithCovariance",
)
FACTOR_MSG_TYPES = (  # every message type `factor_msg` constructs
    *POSE_MSG_TYPES,
    "geometry_msgs/msg/Vector3",
    "geometry_msgs/msg/Twist",
    "geometry_msgs/msg/TwistWithCovariance",
    FACTOR_TYPE,
)
STATUS_CODES = {"metric": 1.0, "scale-free": 2.0, "metric-odometry": 3.0}
IDENTITY = ("query_robot", "query_session", "match_robot", "match_session")


@dataclass(frozen=True)
class LoopFactor:
    """T_match_query of one loop: the query camera's pose in the match camera's optical frame."""

    query_stamp: float  # s
    match_stamp: float  # s
    query_frame_id: str
    match_frame_id: str
    translation: tuple[float, float, float]  # m; a unit vector when not metric
    rotation: tuple[float, float, float, float]  # qx, qy, qz, qw
    covariance: tuple[float, ...]  # 36, row-major (x, y, z, rx, ry, rz), match camera frame
    metric: bool
    inliers: int
    query_id: int = -1
    match_id: int = -1
    # metric, but the length comes from the odometry next to the match keyframe, not from depth
    scale_from_odometry: bool = False
    # who recorded each keyframe ("": the single robot and session of the old format)
    query_robot: str = ""
    query_session: str = ""
    match_robot: str = ""
    match_session: str = ""
    # the rig cameras of the two keyframes (0: the only camera); a rig's factor is between the
    # keyframes' base frames (both frame ids the base frame), a single camera's between cameras
    query_camera: int = 0
    match_camera: int = 0

    def matrix(self) -> np.ndarray:
        """[4, 4] homogeneous T_match_query (maps query-camera points into the match camera)."""
        out = np.eye(4)
        out[:3, :3] = quaternion_matrix(self.rotation)
        out[:3, 3] = self.translation
        return out

    def covariance_matrix(self) -> np.ndarray:
        """[6, 6] in (x, y, z, rx, ry, rz) order: T_true = (Exp(d_rot) R, t + d_t), both
        perturbations along the match camera's axes (ROS convention: the parent frame)."""
        return np.asarray(self.covariance, np.float64).reshape(6, 6)

    def gtsam_covariance(self) -> np.ndarray:
        """[6, 6] in GTSAM Pose3 order (rx, ry, rz, x, y, z) for T_true = T * Exp(xi), xi in the
        query camera frame: xi = (R^T d_rot, R^T d_t) to first order."""
        rt = quaternion_matrix(self.rotation).T
        a = np.zeros((6, 6))
        a[:3, 3:] = rt
        a[3:, :3] = rt
        return a @ self.covariance_matrix() @ a.T


def _get(record: Any, name: str) -> Any:
    return record[name] if isinstance(record, Mapping) else getattr(record, name)


def _text(record: Any, name: str) -> str:
    """A text field that older records (loops.json / loops.csv before issue 22) lack: ""."""
    value = record.get(name) if isinstance(record, Mapping) else getattr(record, name, "")
    return "" if value is None else str(value)


def factor_from_record(record: Any) -> LoopFactor | None:
    """The factor of a ``LoopRecord`` (or its ``record_dict`` / JSON object); None when the
    record has no relative pose (not accepted, or the geometry failed)."""
    status = _get(record, "pose_status")
    cov = tuple(_get(record, "covariance") or ())
    if status not in STATUS_CODES or not _get(record, "accepted") or len(cov) != 36:
        return None
    t = tuple(float(_get(record, k)) for k in ("tx", "ty", "tz"))
    q = tuple(float(_get(record, k)) for k in ("qx", "qy", "qz", "qw"))
    base = _text(record, "pose_frame")  # a rig's loop: between the two keyframes' bases
    return LoopFactor(
        query_stamp=float(_get(record, "query_stamp")),
        match_stamp=float(_get(record, "match_stamp")),
        query_frame_id=base or str(_get(record, "query_frame_id")),
        match_frame_id=base or str(_get(record, "match_frame_id")),
        translation=t,  # type: ignore[arg-type]
        rotation=q,  # type: ignore[arg-type]
        covariance=tuple(float(v) for v in cov),
        metric=status != "scale-free",
        inliers=int(_get(record, "pose_inliers")),
        query_id=int(_get(record, "query_id")),
        match_id=int(_get(record, "match_id")),
        scale_from_odometry=status == "metric-odometry",
        **{name: _text(record, name) for name in IDENTITY},
        query_camera=_camera(record, "query_camera"),
        match_camera=_camera(record, "match_camera"),
    )


def _camera(record: Any, name: str) -> int:
    """A camera index that older records (before issue 49) lack: 0."""
    value = record.get(name) if isinstance(record, Mapping) else getattr(record, name, 0)
    return int(value or 0)


def tag_frame(frame_id: str, robot: str, session: str) -> str:
    """``frame_id`` with the robot and session of its keyframe."""
    return f"{frame_id}@{robot}@{session}"


def untag_frame(text: str) -> tuple[str, str, str]:
    """``tag_frame``'s inverse: (frame_id, robot, session); (text, "", "") for an untagged id.
    A tag is two names by the identity rule (or two empty ones), so a camera frame id holding
    ``@`` that was not tagged stays whole."""
    parts = text.rsplit("@", 2)
    if len(parts) == 3 and (parts[1:] == ["", ""] or _names_ok(parts[1], parts[2])):
        return parts[0], parts[1], parts[2]
    return text, "", ""


def _names_ok(robot: str, session: str) -> bool:
    return name_problem("robot", robot) is None and name_problem("session", session) is None


def _frame_ids(factor: LoopFactor) -> tuple[str, str]:
    """(query, match) frame ids of the message: tagged for a loop between two robot-sessions;
    within one, a frame id holding ``@`` is tagged with two empty names ("cam@x" ->
    "cam@x@@"), so that ``untag_frame`` gives it back whole and the loop stays in its own
    robot-session."""
    query = (factor.query_robot, factor.query_session)
    match = (factor.match_robot, factor.match_session)
    if query == match:
        if "@" not in factor.query_frame_id + factor.match_frame_id:
            return factor.query_frame_id, factor.match_frame_id
        query = match = ("", "")
    return tag_frame(factor.query_frame_id, *query), tag_frame(factor.match_frame_id, *match)


def factor_msg(factor: LoopFactor, types: Mapping[str, Callable[..., Any]]) -> Any:
    """Build the ``nav_msgs/Odometry`` of ``factor`` with the message classes in ``types``
    (keys: ``FACTOR_MSG_TYPES``; rclpy classes or a rosbags typestore's ``types``)."""
    vec, quat = types["geometry_msgs/msg/Vector3"], types["geometry_msgs/msg/Quaternion"]
    q_sec, q_nsec = split_stamp(factor.query_stamp)
    m_sec, m_nsec = split_stamp(factor.match_stamp)
    query_frame, match_frame = _frame_ids(factor)
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=q_sec, nanosec=q_nsec),
        frame_id=match_frame,
    )
    x, y, z = (float(v) for v in factor.translation)
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](x=x, y=y, z=z),
        orientation=quat(**dict(zip("xyzw", (float(v) for v in factor.rotation), strict=True))),
    )
    twist = types["geometry_msgs/msg/Twist"](
        linear=vec(x=float(m_sec), y=float(m_nsec), z=STATUS_CODES[_status(factor)]),
        angular=vec(x=float(factor.inliers), y=float(factor.query_id), z=float(factor.match_id)),
    )
    return types[FACTOR_TYPE](
        header=header,
        child_frame_id=query_frame,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose, covariance=np.asarray(factor.covariance, np.float64)
        ),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=twist, covariance=_camera_slots(factor)
        ),
    )


def _camera_slots(factor: LoopFactor) -> np.ndarray:
    """twist.covariance: [0] the query's rig camera, [1] the match's, the rest zeros."""
    out = np.zeros(36)
    out[:2] = factor.query_camera, factor.match_camera
    return out


def _status(factor: LoopFactor) -> str:
    if not factor.metric:
        return "scale-free"
    return "metric-odometry" if factor.scale_from_odometry else "metric"


def _cameras_of(twist: Any) -> tuple[int, int]:
    """The rig cameras in twist.covariance[0], [1]; (0, 0) where there are none (a message of
    an older node) or they are no camera indices."""
    try:
        slots = [float(v) for v in list(getattr(twist, "covariance", ()))[:2]]
    except (TypeError, ValueError):
        return 0, 0
    cams = [int(v) if math.isfinite(v) and 0 <= v < 2**31 else 0 for v in (*slots, 0.0, 0.0)]
    return cams[0], cams[1]


def factor_from_msg(msg: Any) -> LoopFactor:
    """Decode a ``loop_closure/factor`` message (rclpy or rosbags ``nav_msgs/Odometry``)."""
    stamp, twist = msg.header.stamp, msg.twist.twist
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    cov = tuple(float(v) for v in msg.pose.covariance)
    if len(cov) != 36 or twist.linear.z not in STATUS_CODES.values():
        raise ValueError(
            f"not a loop_closure/factor message: covariance has {len(cov)} values, status code "
            f"{twist.linear.z} (expected 36 values and 1.0, 2.0 or 3.0)"
        )
    query_frame, query_robot, query_session = untag_frame(msg.child_frame_id)
    match_frame, match_robot, match_session = untag_frame(msg.header.frame_id)
    ints = (twist.angular.x, twist.angular.y, twist.angular.z)
    if not all(math.isfinite(v) for v in ints):  # inliers and keyframe ids: int() would fail
        raise ValueError(f"not a loop_closure/factor message: twist.angular {ints} not finite")
    cams = _cameras_of(msg.twist)
    return LoopFactor(
        query_stamp=stamp.sec + stamp.nanosec * 1e-9,
        match_stamp=twist.linear.x + twist.linear.y * 1e-9,
        query_frame_id=query_frame,
        match_frame_id=match_frame,
        translation=(p.x, p.y, p.z),
        rotation=(q.x, q.y, q.z, q.w),
        covariance=cov,
        metric=twist.linear.z != STATUS_CODES["scale-free"],
        inliers=int(twist.angular.x),
        query_id=int(twist.angular.y),
        match_id=int(twist.angular.z),
        scale_from_odometry=twist.linear.z == STATUS_CODES["metric-odometry"],
        query_robot=query_robot,
        query_session=query_session,
        match_robot=match_robot,
        match_session=match_session,
        query_camera=cams[0],
        match_camera=cams[1],
    )
