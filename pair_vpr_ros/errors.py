"""Every error this package raises on purpose.

Each message says what went wrong, where (file, topic, parameter) and what to do about it.
Lower-level exceptions are chained with ``raise ... from err``. A full disk is said as one
(`disk_full`, `os_reason`) wherever it surfaces: an OSError, SQLite or a Milvus call.
"""

from __future__ import annotations

import errno

_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
_FULL_TEXTS = ("database or disk is full", "no space left on device", "disk quota exceeded")


class PairVPRError(Exception):
    """Base class: catch this to handle any user-facing error of the package."""


class UsageError(PairVPRError):
    """A command line is wrong beyond what argparse checks (missing or conflicting options)."""


class CheckpointError(PairVPRError):
    """A weights file is missing, unreadable, truncated or does not fit the network."""


class ConfigError(PairVPRError):
    """A configuration value or parameter is out of range or inconsistent."""


class ImageConversionError(PairVPRError):
    """An image message cannot be turned into an RGB array (unsupported or malformed)."""


class ImageTooLargeError(ImageConversionError):
    """An image has more pixels than the configured limit (max_image_pixels); it is skipped."""


class MapError(PairVPRError):
    """A place map directory is missing, corrupt, of another version or another model."""


class MapFingerprintError(MapError):
    """A saved map was built with another model (checkpoint, input size or descriptor dim)."""


class MapUnavailableError(MapError):
    """The map's index server (Milvus) cannot be reached now: the query is skipped and counted;
    keyframes added meanwhile are kept and inserted when it answers again."""


class BagError(PairVPRError):
    """A rosbag is missing, not a bag, corrupt, or lacks the requested topics."""


class OutputError(PairVPRError):
    """An output cannot be written where asked (a file where a folder is expected, read-only,
    disk full), or would replace data (an existing map) without being told to."""


class DatasetError(PairVPRError):
    """A training or evaluation dataset folder is missing or not in the expected layout."""


class TrainingError(PairVPRError):
    """Training cannot go on: the loss became NaN/inf or a resumed run does not fit its config."""


class PoseGraphError(PairVPRError):
    """Pose-graph input cannot be used: no odometry, unreadable loops, trajectories that share
    no stamps."""


class GeometryInputError(PairVPRError):
    """Camera intrinsics or a depth image are missing, malformed or do not fit the image."""


class FleetMessageError(PairVPRError):
    """A fleet message (another robot's descriptor, score request or response) cannot be used.
    `reason` is the short key receivers count it under ("malformed", "wrong model", ...)."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


def disk_full(err: BaseException) -> bool:
    """Whether `err` (an OSError, a sqlite3 error, a pymilvus error wrapping an OSError) says the
    disk (or the user's quota) is full: SQLITE_FULL is "database or disk is full", which is
    never a damaged database."""
    if isinstance(err, OSError) and err.errno in _FULL_ERRNOS:
        return True
    if getattr(err, "sqlite_errorcode", None) == 13:  # SQLITE_FULL
        return True
    text = f"{err} {getattr(err, 'message', '')}".lower()
    return any(t in text for t in _FULL_TEXTS)


def os_reason(err: BaseException) -> str:
    """A low-level error in words: "the disk is full (No space left on device)" for a full
    disk, else its strerror (an OSError) or its text; never "(None)"."""
    text = (err.strerror if isinstance(err, OSError) else None) or str(err)
    return f"the disk is full ({text})" if disk_full(err) else text
