"""Camera images to RGB uint8 `[H, W, 3]`, ROS-free: raw and compressed `sensor_msgs` images
(rclpy or rosbags messages, duck-typed) and image files.

`convert.msg_to_rgb` is the entry point; `raw` holds the `Image` encodings, `encoded` the
`CompressedImage` codecs and image files, `pixels` the size limit and robust scaling to uint8;
`thumbnails` keeps keyframe images as small JPEGs for loop images.
"""

from pair_vpr_ros.images.convert import msg_to_rgb
from pair_vpr_ros.images.encoded import IMAGE_SUFFIXES, compressed_to_rgb, file_to_rgb
from pair_vpr_ros.images.pixels import MAX_PIXELS
from pair_vpr_ros.images.raw import SUPPORTED_ENCODINGS, image_to_rgb
from pair_vpr_ros.images.thumbnails import FolderThumbnails, MemoryThumbnails, Thumbnail

__all__ = [
    "IMAGE_SUFFIXES",
    "FolderThumbnails",
    "MemoryThumbnails",
    "Thumbnail",
    "MAX_PIXELS",
    "SUPPORTED_ENCODINGS",
    "compressed_to_rgb",
    "file_to_rgb",
    "image_to_rgb",
    "msg_to_rgb",
]
