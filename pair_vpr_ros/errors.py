"""Every error this package raises on purpose.

Each message says what went wrong, where (file, topic, parameter) and what to do about it.
Lower-level exceptions are chained with ``raise ... from err``.
"""

from __future__ import annotations


class PairVPRError(Exception):
    """Base class: catch this to handle any user-facing error of the package."""


class CheckpointError(PairVPRError):
    """A weights file is missing, unreadable, truncated or does not fit the network."""


class ConfigError(PairVPRError):
    """A configuration value or parameter is out of range or inconsistent."""


class ImageConversionError(PairVPRError):
    """An image message cannot be turned into an RGB array (unsupported or malformed)."""


class MapError(PairVPRError):
    """A place map directory is missing, corrupt, of another version or another model."""


class MapFingerprintError(MapError):
    """A saved map was built with another model (checkpoint, input size or descriptor dim)."""


class BagError(PairVPRError):
    """A rosbag is missing, not a bag, corrupt, or lacks the requested topics."""


class DatasetError(PairVPRError):
    """A training or evaluation dataset folder is missing or not in the expected layout."""


class TrainingError(PairVPRError):
    """Training cannot go on: the loss became NaN/inf or a resumed run does not fit its config."""
