"""Small JPEG copies of keyframe images, kept so that a loop's match can be shown later: in memory
within a byte budget (`MemoryThumbnails`, the node's loop image) or as files in a folder
(`FolderThumbnails`, the replay's report). A map keeps no images, so a keyframe of a loaded or
prior map, or of another robot, has none (`get` says None).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np


@dataclass(frozen=True)
class Thumbnail:
    """An image `rgb` [h, w, 3] uint8 and its `scale`: its pixels per pixel of the original, so
    a point (x, y) of the original lies at (x * scale, y * scale)."""

    rgb: np.ndarray
    scale: float


def shrink(rgb: np.ndarray, max_side: int) -> Thumbnail:
    """`rgb` [H, W, 3] uint8 scaled down (area filter) so that its longer side is at most
    `max_side` pixels; never enlarged."""
    h, w = rgb.shape[:2]
    scale = min(1.0, max_side / max(h, w, 1))
    if scale >= 1.0:
        return Thumbnail(rgb, 1.0)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    return Thumbnail(small, size[0] / w)


def to_jpeg(rgb: np.ndarray, quality: int = 80) -> bytes:
    """RGB uint8 [h, w, 3] -> JPEG bytes."""
    ok, data = cv2.imencode(
        ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality]
    )
    if not ok:  # only for an empty image, which no keyframe is
        raise ValueError(f"cannot encode an image of shape {rgb.shape} as JPEG")
    return data.tobytes()


def from_jpeg(data: bytes) -> np.ndarray | None:
    """JPEG bytes -> RGB uint8 [h, w, 3]; None when they do not decode."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return None if image is None else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


class MemoryThumbnails:
    """Keyframe images by key (a keyframe id) as JPEG in memory, at most `max_bytes` of them:
    the oldest go first. Each is stored with its stamp and returned only for the same stamp,
    so a map cleared or loaded (ids starting again) never shows another keyframe's image."""

    def __init__(self, max_bytes: int, max_side: int = 320, quality: int = 80) -> None:
        self.max_bytes, self.max_side, self.quality = max_bytes, max_side, quality
        self._items: OrderedDict[int, tuple[float, float, bytes]] = OrderedDict()
        self.nbytes = 0

    def __len__(self) -> int:
        return len(self._items)

    def put(self, key: int, stamp: float, rgb: np.ndarray) -> None:
        if self.max_bytes <= 0:
            return
        thumb = shrink(rgb, self.max_side)
        data = to_jpeg(thumb.rgb, self.quality)
        self._drop(key)
        self._items[key] = (stamp, thumb.scale, data)
        self.nbytes += len(data)
        while self.nbytes > self.max_bytes and self._items:
            self._drop(next(iter(self._items)))

    def get(self, key: int, stamp: float) -> Thumbnail | None:
        item = self._items.get(key)
        if item is None or item[0] != stamp:
            return None
        rgb = from_jpeg(item[2])
        return None if rgb is None else Thumbnail(rgb, item[1])

    def _drop(self, key: int) -> None:
        item = self._items.pop(key, None)
        if item is not None:
            self.nbytes -= len(item[2])


class FolderThumbnails:
    """Images by key (an int) as JPEG files under `root`, 1,000 a sub-folder
    (`0012/12345.jpg`), written as they come; only their scales stay in memory."""

    def __init__(self, root: str | Path, max_side: int = 256, quality: int = 75) -> None:
        self.root, self.max_side, self.quality = Path(root), max_side, quality
        self._scales: dict[int, float] = {}
        self.nbytes = 0

    @staticmethod
    def name(key: int) -> str:
        """The file of `key`, relative to the root."""
        return f"{key // 1000:04d}/{key}.jpg"

    def put(self, key: int, rgb: np.ndarray) -> Thumbnail:
        """Write the image of `key`; -> the thumbnail written."""
        thumb = shrink(rgb, self.max_side)
        data = to_jpeg(thumb.rgb, self.quality)
        path = self.root / self.name(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        self._scales[key] = thumb.scale
        self.nbytes += len(data)
        return thumb

    def __contains__(self, key: int) -> bool:
        return key in self._scales

    def get(self, key: int) -> Thumbnail | None:
        if key not in self._scales:
            return None
        try:
            rgb = from_jpeg((self.root / self.name(key)).read_bytes())
        except OSError:
            return None
        return None if rgb is None else Thumbnail(rgb, self._scales[key])
