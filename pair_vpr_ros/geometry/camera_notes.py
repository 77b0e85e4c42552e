"""What the node and the replay say once about their camera inputs, ROS-free: fallback
intrinsics without distortion, a camera_info topic that stays silent, the demo model on images
that are not the demo world's.

An ignored lens distortion or a wrong focal length gives confident wrong poses (on real RGB-D
pairs with a radial k1 of 0.2 left out, rotations 1-4 deg off; docs/real-cameras.md): the pose
code scales the covariance of a pose whose PnP and essential-matrix rotations disagree, but the
user should know the cause at start-up rather than from the covariances.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.hashing import sha256_file

CAMERA_INFO_WAIT_S = 5.0  # seconds after the first frame before a silent camera_info is reported
DEMO_WEIGHTS = Path(__file__).resolve().parents[1] / "demo" / "assets" / "demo-small.pth"
DEMO_SIZE = (320, 240)  # the demo world's images (demo/world.py WorldConfig)


def fallback_intrinsics_note(values: Mapping[str, Any]) -> str:
    """The note for a parameter set (node parameters) whose relative poses will use the
    fallback camera_* intrinsics without any distortion; "" otherwise."""
    if not values.get("relative_pose", True) or values.get("camera_info_topic"):
        return ""
    if values.get("camera_fx", 0.0) <= 0:
        return ("relative poses are off: neither camera_info_topic nor the camera_* intrinsics "
                "are set")  # fmt: skip
    if values.get("camera_distortion", "").strip():
        return ""
    return ("relative poses use the fallback camera_* intrinsics with no distortion: a real lens "
            "has some, and an ignored distortion bends the poses (their covariances grow when "
            "PnP and the essential matrix disagree); set camera_distortion and "
            "camera_distortion_model from a calibration, or camera_info_topic")  # fmt: skip


def camera_info_silence_note(topic: str, waited_s: float, fallback: bool) -> str:
    """The note for a camera_info topic that sent nothing valid within `waited_s` seconds."""
    then = ("the fallback camera_* intrinsics are used meanwhile" if fallback else
            "no relative poses until it does (or set the camera_* intrinsics)")  # fmt: skip
    return (
        f"camera_info_topic {topic}: no valid CameraInfo within {waited_s:.0f} s of the "
        f"first frame: is the topic name right and the driver publishing? {then}"
    )


@lru_cache(maxsize=1)
def demo_weights_id() -> str:
    """The weights id (``sha256:`` + 16 hex) of the shipped demo model; "" when not installed."""
    try:
        return f"sha256:{sha256_file(DEMO_WEIGHTS)[:16]}"
    except OSError:
        return ""


def demo_model_note(
    fingerprint: str, rgb: np.ndarray, demo_size: tuple[int, int] = DEMO_SIZE
) -> str:
    """The note for the shipped demo model (trained on the synthetic demo world only; the
    model's `fingerprint` starts with its weights id) run on images that are not the demo
    world's (another size than `demo_size` (W, H)); "" otherwise."""
    demo = demo_weights_id()
    if not demo or not fingerprint.startswith(demo):
        return ""
    if (rgb.shape[1], rgb.shape[0]) == tuple(demo_size):
        return ""
    return (
        f"the weights are the shipped demo model, trained on the synthetic demo world's "
        f"{demo_size[0]}x{demo_size[1]} images only; these images are "
        f"{rgb.shape[1]}x{rgb.shape[0]}: real cameras need a real checkpoint (the authors' "
        "pairvpr-vitB.pth, see the README)"
    )
