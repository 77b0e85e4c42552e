"""ROS-free conversion of ``sensor_msgs/Image`` and ``CompressedImage`` data to RGB uint8.

Every function returns a fresh C-contiguous ``np.ndarray [H, W, 3] uint8`` in RGB order that never
shares memory with the message, and raises :class:`~pair_vpr_ros.errors.ImageConversionError`
(naming the encoding, the sizes and what is wrong) for anything unsupported or malformed.

Raw ``Image`` encodings (``SUPPORTED_ENCODINGS``, matched case-insensitively):

- 8-bit colour: ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``8UC3`` (= bgr8), ``8UC4`` (= bgra8);
  alpha is dropped.
- 16-bit colour: ``rgb16``, ``bgr16``, ``rgba16``, ``bgra16``, ``16UC3`` (= bgr16),
  ``16UC4`` (= bgra16): the high byte is kept (``>> 8``), as cv_bridge does.
- grey: ``mono8``, ``8UC1``; ``mono16``, ``16UC1``, ``32FC1`` are scaled (see below).
- Bayer: ``bayer_{rggb,bggr,gbrg,grbg}8`` and ``...16`` (demosaiced by OpenCV, 16-bit ``>> 8``).
- YUV: ``uyvy`` / ``yuv422`` (U Y V Y), ``yuyv`` / ``yuv422_yuy2`` (Y U Y V) need an even width;
  ``nv21`` / ``nv12`` (a Y plane of ``height`` rows then an interleaved VU / UV plane of
  ``height / 2`` rows, all rows ``step`` bytes apart) need even height and width.

Rows are read through ``step`` (padding allowed) and ``is_bigendian`` selects the byte order of
16-bit and float samples.

Scaling of mono16 / 16UC1 / 32FC1 (and of single-channel 16-bit PNGs and compressedDepth): the
range is the 1st..99th percentile of the finite values of a subsample (about 16k pixels, every s-th
row and column), so that a few hot pixels or far-away depth readings do not wash the image out; it
falls back to the full finite min..max when those percentiles are equal. Values are mapped linearly
to 0..255 and clipped; non-finite pixels become 0 and an image without contrast is all 0.

``CompressedImage`` formats: ``"jpeg"``, ``"jpg"``, ``"png"`` (also ``tiff``, ``webp``, ``bmp``),
the image_transport form ``"<enc>; jpeg compressed bgr8"`` and
``"<16UC1|32FC1>; compressedDepth png"`` (a 12-byte header before the PNG; 32FC1 depth is recovered
from the quantised inverse depth). Decoded colour is BGR(A) and becomes RGB, grey becomes RGB,
single-channel 16-bit is scaled as above and 16-bit colour is ``>> 8``.

Size limit: an image of more than ``max_pixels`` (width * height, default ``MAX_PIXELS`` = 50
megapixels, the node's ``max_image_pixels``) raises ``ImageTooLargeError`` before anything is
decoded: a 388 KB PNG can claim 20000 x 20000 pixels (1.2 GB as RGB). PNG, JPEG, BMP and WebP
sizes are read from the header; other codecs (TIFF) are checked right after decoding.

The work is split by concept: ``pixels`` (bytes, size limit, scaling), ``raw`` (``Image``
encodings), ``encoded`` (``CompressedImage`` and image files); this module is the entry point.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pair_vpr_ros.errors import ImageConversionError
from pair_vpr_ros.images.encoded import compressed_to_rgb
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.images.raw import image_to_rgb


def msg_to_rgb(msg: Any, max_pixels: int = MAX_PIXELS) -> np.ndarray:
    """An Image (has ``.encoding``) or CompressedImage (has ``.format``) -> RGB uint8 [H, W, 3].

    Works with rclpy messages (``data`` as ``array.array``, bytes or list) and rosbags messages
    (``data`` as a uint8 numpy array). Larger than `max_pixels`: ImageTooLargeError.
    """
    kind = type(msg).__name__
    try:
        if hasattr(msg, "encoding"):
            fields = (msg.encoding, msg.height, msg.width, msg.step, msg.data)
            big = bool(getattr(msg, "is_bigendian", False))
            return image_to_rgb(*fields, is_bigendian=big, max_pixels=max_pixels)
        if hasattr(msg, "format"):
            fmt, data = msg.format, msg.data
            return compressed_to_rgb(fmt, data, max_pixels=max_pixels)
    except AttributeError as err:
        raise ImageConversionError(f"{kind} message lacks a field: {err}") from err
    raise ImageConversionError(
        f"{kind} is neither a sensor_msgs/Image (no .encoding) nor a CompressedImage (no .format)"
    )
