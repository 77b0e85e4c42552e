"""A rig: several cameras on one robot, one map (issue 49).

Each camera has a name, its topics (image, camera_info, depth or the right image of a stereo
pair) and its pose in the robot's base frame, ``camera_to_base`` (x, y, z, qx, qy, qz, qw; the
camera's optical frame: x right, y down, z forward). Its index in ``Rig.cameras`` is the camera
id every keyframe of the map records (0: the first camera, and the only one of a single-camera
node and of maps made before rigs). Frames of all cameras taken within ``stamp_tolerance`` of one
another form one rig keyframe (`rig_frames.RigAssembler`), encoded as one batch.

A loop between camera a (took the match) and camera b (took the query) is posed between the
two cameras (``T_a_b``, geometry/relpose.py) and then given between the two keyframes' base
poses, ``T_base_a T_a_b T_b_base`` (`to_base`), its covariance carried through to first order,
so a pose graph over base poses takes it without knowing the cameras.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.geometry.rotations import matrix_quaternion, quaternion_matrix, skew
from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.types import Pose

NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")  # a camera name: one ROS name token
TOPICS = ("image_topic", "camera_info_topic", "depth_topic", "right_topic",
          "right_camera_info_topic")  # fmt: skip
MAX_TOLERANCE_S = 1.0


@dataclass(frozen=True)
class RigCamera:
    """One camera of a rig. Topics "" are not used (image_topic "": `<name>/image`, as the
    node subscribes it). frame_id "": whatever the images say (then checked as they come)."""

    name: str
    camera_to_base: Pose | None = None
    frame_id: str = ""
    image_topic: str = ""
    camera_info_topic: str = ""
    depth_topic: str = ""
    right_topic: str = ""
    right_camera_info_topic: str = ""


@dataclass(frozen=True)
class Rig:
    """The cameras (their order gives the camera ids), the stamp tolerance (s) of one rig
    keyframe, how long the node waits for a late camera (s, wall clock) and the base frame id
    that rig loops are given in."""

    cameras: tuple[RigCamera, ...] = ()
    stamp_tolerance: float = 0.02
    max_delay: float = 0.2
    base_frame: str = "base_link"
    _index: dict[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.check()
        object.__setattr__(self, "_index", {c.name: i for i, c in enumerate(self.cameras)})

    def check(self) -> None:
        """ConfigError naming the first problem (what, which camera, what to do)."""
        if not self.cameras:
            raise ConfigError("a rig needs at least one camera (cameras: [front, rear])")
        names = [c.name for c in self.cameras]
        for cam in self.cameras:
            if not NAME.fullmatch(cam.name):
                raise ConfigError(f"rig camera name {cam.name!r} must be letters, digits and "
                                  "_, from a letter (it names the camera's topics)")  # fmt: skip
            if names.count(cam.name) > 1:
                raise ConfigError(f"rig camera {cam.name!r} is listed twice: give each camera "
                                  "its own name")  # fmt: skip
            if len(self.cameras) > 1 and cam.camera_to_base is None:
                raise ConfigError(
                    f"rig camera {cam.name!r} has no extrinsic: give its camera_to_base (x, y, z, "
                    "qx, qy, qz, qw: the camera's optical frame in the base frame), or publish it "
                    "on /tf_static (node), so that its loops can be given in the base frame"
                )
            if cam.camera_to_base is not None:
                check_pose(cam.camera_to_base, f"rig camera {cam.name!r} camera_to_base")
        check_frame_ids({c.name: c.frame_id for c in self.cameras if c.frame_id})
        tol = self.stamp_tolerance
        if not (math.isfinite(tol) and 0 <= tol <= MAX_TOLERANCE_S):
            raise ConfigError(f"rig stamp_tolerance {tol!r} must be seconds in [0, "
                              f"{MAX_TOLERANCE_S:g}]")  # fmt: skip
        if not (math.isfinite(self.max_delay) and 0 <= self.max_delay <= 10):
            raise ConfigError(f"rig max_delay {self.max_delay!r} must be seconds in [0, 10]")
        if not self.base_frame or "@" in self.base_frame:
            raise ConfigError(f"rig base_frame {self.base_frame!r} must be a frame id (no '@')")

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def index(self, name: str) -> int:
        return self._index[name]

    def name(self, camera: int) -> str:
        """The name of camera id `camera` ("camera N" for an id the rig does not have: a map
        made with a larger rig)."""
        return self.cameras[camera].name if 0 <= camera < len(self.cameras) else f"camera {camera}"

    def with_extrinsic(self, name: str, pose: Pose) -> Rig:
        """This rig with camera `name`'s camera_to_base set (read from /tf_static)."""
        cams = tuple(replace(c, camera_to_base=tuple(pose)) if c.name == name else c
                     for c in self.cameras)  # fmt: skip
        return replace(self, cameras=cams)


def check_pose(pose: Sequence[float], what: str) -> Pose:
    """7 finite numbers with a non-zero quaternion -> a Pose (normalised quaternion)."""
    try:
        values = [float(v) for v in pose]
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{what} must be 7 numbers (x, y, z, qx, qy, qz, qw): {pose!r}") from err
    if len(values) != 7 or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{what} must be 7 finite numbers (x, y, z, qx, qy, qz, qw), got "
                          f"{values}")  # fmt: skip
    norm = math.sqrt(sum(v * v for v in values[3:]))
    if norm < 1e-9:
        raise ConfigError(f"{what} has a zero quaternion: {values}")
    return (*values[:3], *(v / norm for v in values[3:]))  # type: ignore[return-value]


def check_frame_ids(frame_ids: Mapping[str, str]) -> None:
    """ConfigError when two cameras (name -> image frame id) share a frame id: their images
    could not be told apart in tf, nor their loops' frames."""
    seen: dict[str, str] = {}
    for name, frame_id in frame_ids.items():
        if frame_id in seen:
            raise ConfigError(
                f"rig cameras {seen[frame_id]!r} and {name!r} have one frame id {frame_id!r}: "
                "each camera's images need their own frame_id (set it in the camera driver)"
            )
        seen[frame_id] = name


def parse_rig(data: Any, where: str) -> tuple[list[RigCamera], dict[str, Any]]:
    """A rig file's content (YAML: ``cameras: [{name, camera_to_base, image_topic, ...}]``,
    optional ``stamp_tolerance``, ``max_delay``, ``base_frame``) -> its cameras and the Rig's
    other settings; a camera may lack camera_to_base (to come from tf). ConfigError naming
    `where` (the file) otherwise."""
    if not isinstance(data, Mapping) or not isinstance(data.get("cameras"), list):
        raise ConfigError(f"{where}: a rig file needs a list 'cameras' of cameras, each with "
                          "'name' and 'camera_to_base' (and its topics)")  # fmt: skip
    allowed = {"name", "camera_to_base", "frame_id", *TOPICS}
    cams = []
    for i, item in enumerate(data["cameras"]):
        if not isinstance(item, Mapping) or "name" not in item:
            raise ConfigError(f"{where}: camera {i} must be a mapping with a 'name'")
        unknown = sorted(set(item) - allowed)
        if unknown:
            raise ConfigError(f"{where}: camera {item['name']!r} has unknown keys {unknown} "
                              f"(known: {sorted(allowed)})")  # fmt: skip
        pose = item.get("camera_to_base")
        if pose is not None:
            pose = check_pose(pose, f"{where}: camera {item['name']!r} camera_to_base")
        text = {k: str(item.get(k) or "") for k in ("frame_id", *TOPICS)}
        cams.append(RigCamera(str(item["name"]), pose, **text))
    extra = sorted(set(data) - {"cameras", "stamp_tolerance", "max_delay", "base_frame"})
    if extra:
        raise ConfigError(f"{where}: unknown keys {extra} (known: cameras, stamp_tolerance, "
                          "max_delay, base_frame)")  # fmt: skip
    try:
        settings = {k: float(data[k]) for k in ("stamp_tolerance", "max_delay") if k in data}
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{where}: stamp_tolerance and max_delay are seconds: {err}") from err
    if "base_frame" in data:
        settings["base_frame"] = str(data["base_frame"])
    return cams, settings


def rig_from_dict(data: Any, where: str) -> Rig:
    """`parse_rig`, every camera with its extrinsic -> Rig (ConfigError naming `where`)."""
    cams, settings = parse_rig(data, where)
    try:
        return Rig(tuple(cams), **settings)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from err


# ---- loops in the base frame ---------------------------------------------------------------
def _matrix(pose: Sequence[float]) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = quaternion_matrix(pose[3:])
    out[:3, 3] = pose[:3]
    return out


def compose_base(
    t_a_b: np.ndarray, cov: np.ndarray, base_a: Sequence[float], base_b: Sequence[float]
) -> tuple[np.ndarray, np.ndarray]:
    """``T_base_a T_a_b T_b_base`` [4, 4] and its covariance [6, 6] (x, y, z, rx, ry, rz; errors
    along the parent frame's axes, as `LoopRecord`'s: R' = Exp(d_r) R, t' = t + d_t).

    With B = T_b_base = (Rb, tb): t_base = Ra (R tb + t) + ta and R_base = Ra R Rb, so
    d_t_base = Ra d_t - Ra [R tb]x d_r and d_r_base = Ra d_r to first order."""
    a, b_inv = _matrix(base_a), np.linalg.inv(_matrix(base_b))
    out = a @ t_a_b @ b_inv
    ra, lever = a[:3, :3], t_a_b[:3, :3] @ b_inv[:3, 3]
    jac = np.zeros((6, 6))
    jac[:3, :3], jac[:3, 3:], jac[3:, 3:] = ra, -ra @ skew(lever), ra
    return out, jac @ cov @ jac.T


def to_base(record: LoopRecord, rig: Rig) -> None:
    """Give a posed `record`'s T_match_query between the two keyframes' base poses (in place):
    pose fields, covariance and ``pose_frame`` = the rig's base frame. A record without a pose,
    or of a camera the rig has no extrinsic for (a map made with a larger rig), is left as it
    is (between the camera frames, ``pose_frame`` "")."""
    n = len(rig.cameras)
    if not record.pose_status or not (0 <= record.match_camera < n and
                                      0 <= record.query_camera < n):  # fmt: skip
        return
    base_a = rig.cameras[record.match_camera].camera_to_base
    base_b = rig.cameras[record.query_camera].camera_to_base
    if base_a is None or base_b is None:
        return
    t = _matrix((record.tx, record.ty, record.tz, record.qx, record.qy, record.qz, record.qw))
    cov = np.asarray(record.covariance, dtype=np.float64).reshape(6, 6)
    out, cov = compose_base(t, cov, base_a, base_b)
    record.tx, record.ty, record.tz = (float(v) for v in out[:3, 3])
    record.qx, record.qy, record.qz, record.qw = matrix_quaternion(out[:3, :3])
    record.covariance = tuple(float(v) for v in (cov + cov.T).ravel() / 2)
    record.pose_frame = rig.base_frame


def static_chain(
    edges: Mapping[str, tuple[str, Sequence[float]]], base: str, frame: str
) -> Pose | None:
    """The pose of `frame` in `base` from static transforms (tf: child -> (parent, pose of the
    child in the parent)), composed along the chain; None when `frame` does not lead to `base`."""
    out, seen = np.eye(4), set()
    while frame != base:
        if frame not in edges or frame in seen:
            return None
        seen.add(frame)
        parent, pose = edges[frame]
        out = _matrix(pose) @ out
        frame = parent
    return (*(float(v) for v in out[:3, 3]), *matrix_quaternion(out[:3, :3]))  # type: ignore
