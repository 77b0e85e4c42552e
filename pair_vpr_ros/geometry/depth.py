"""Depth images: ``sensor_msgs/Image`` 16UC1 (millimetres) or 32FC1 (metres) -> float32 metres.

REP 118: 16UC1 holds millimetres with 0 = no measurement; 32FC1 holds metres with NaN (or
+-inf) = no measurement. Both come back as float32 metres with NaN where there is none. The depth
must be aligned with the colour image (same size, same optical frame; e.g. a driver's
``aligned_depth_to_color`` topic).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pair_vpr_ros.errors import GeometryInputError, ImageConversionError
from pair_vpr_ros.images.raw import image_samples

DEPTH_SCALE = {"16uc1": 1e-3, "mono16": 1e-3, "32fc1": 1.0}  # -> metres


def depth_from_msg(msg: Any) -> np.ndarray:
    """A depth ``sensor_msgs/Image`` (rclpy or rosbags; rows padded to ``step`` allowed) ->
    [H, W] float32 metres, NaN where there is no measurement; GeometryInputError if malformed."""
    encoding = str(msg.encoding)
    scale = DEPTH_SCALE.get(encoding.strip().lower())
    if scale is None:
        raise GeometryInputError(
            f"depth image encoding {encoding!r} is not supported: use 16UC1 (mm) or 32FC1 (m)"
        )
    try:
        view, _, _ = image_samples(
            encoding, msg.height, msg.width, msg.step, msg.data, bool(msg.is_bigendian)
        )
    except ImageConversionError as err:
        raise GeometryInputError(f"depth image: {err}") from err
    values = view[:, :, 0].astype(np.float32) * np.float32(scale)
    values[~np.isfinite(values) | (values <= 0)] = np.nan  # 16UC1 0 and 32FC1 NaN/inf: none
    return values
