"""`vpr_node`'s rig parameters (issue 49), ROS-free.

The table's ``cameras`` names the cameras (``[front, rear]``; empty: the one camera of
``image_topic``). Each camera ``<name>`` then has the parameters of `CAMERA_PARAMS` under its
name, declared by the node once it knows the names: in a parameter file a mapping ``<name>:``
in ``ros__parameters``, on the command line ``-p rear.camera_to_base:=[...]``. The table's
``base_frame``, ``rig_stamp_tolerance`` and ``rig_max_delay`` are the `loops.rig.Rig`'s settings.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.loops.rig import RigCamera, check_pose

# per-camera text parameters: name -> (default, "{name}" = the camera's name; description)
CAMERA_PARAMS: dict[str, tuple[str, str]] = {
    "image_topic": ("{name}/image", "sensor_msgs/Image of the camera (remap it, or set this)"),
    "camera_info_topic": ("{name}/camera_info", "its sensor_msgs/CameraInfo ('' = none: no "
                          "relative poses for its loops)"),
    "depth_topic": ("", "its aligned depth image (16UC1 mm or 32FC1 m; '' = none)"),
    "right_image_topic": ("", "stereo: its rectified right image ('' = none)"),
    "right_camera_info_topic": ("", "stereo: the right camera's CameraInfo (the baseline)"),
    "frame_id": ("", "the frame id of its images, its frame in tf ('' = what the images say; "
                 "needed to read camera_to_base from /tf_static)"),
}  # fmt: skip
CAMERA_TO_BASE = "camera_to_base"  # 7 doubles per camera; unset: read from /tf_static
CAMERA_TO_BASE_HELP = (
    "pose of the camera's optical frame (x right, y down, z forward) in base_frame: x, y, z, "
    "qx, qy, qz, qw (unset: from /tf_static, base_frame -> frame_id)"
)


def camera_defaults(name: str) -> dict[str, str]:
    """Camera `name`'s text parameters and their defaults (``<name>.image_topic``: ...)."""
    return {f"{name}.{k}": d.format(name=name) for k, (d, _) in CAMERA_PARAMS.items()}


def rig_cameras(names: Sequence[str], values: Mapping[str, Any]) -> list[RigCamera]:
    """The cameras of `names` from their parameters (`values`: ``<name>.<param>`` -> value,
    ``<name>.camera_to_base`` () or absent when unset); ConfigError for a bad extrinsic."""
    cams = []
    for name in names:
        pose = tuple(values.get(f"{name}.{CAMERA_TO_BASE}") or ())
        where = f"parameter {name}.{CAMERA_TO_BASE}"
        text = {k: str(values.get(f"{name}.{k}", camera_defaults(name)[f"{name}.{k}"]))
                for k in CAMERA_PARAMS}  # fmt: skip
        text["right_topic"] = text.pop("right_image_topic")
        cams.append(RigCamera(name, check_pose(pose, where) if pose else None, **text))
    return cams


def rig_settings(values: Mapping[str, Any]) -> dict[str, Any]:
    """The Rig's settings from the table's values."""
    return dict(stamp_tolerance=float(values["rig_stamp_tolerance"]),
                max_delay=float(values["rig_max_delay"]),
                base_frame=str(values["base_frame"]))  # fmt: skip


def camera_sections(given: Mapping[str, Any]) -> dict[str, Mapping[str, Any]]:
    """A parameter file's per-camera mappings (``front: {image_topic: ...}``) of the cameras
    its ``cameras`` lists; ConfigError for a key no camera parameter has."""
    names = given.get("cameras") or ()
    out = {n: given[n] for n in names if isinstance(given.get(n), Mapping)}
    known = {*CAMERA_PARAMS, CAMERA_TO_BASE}
    for name, section in out.items():
        unknown = sorted(set(section) - known)
        if unknown:
            raise ConfigError(f"camera {name!r} has unknown parameters {unknown} (known: "
                              f"{', '.join(sorted(known))})")  # fmt: skip
    return out
