"""Opening a rosbag: the path checked (cheaply, before slow work), the reader, hints on failure.

Reads rosbag2 folders (mcap or sqlite3 storage), bare ``.mcap`` / ``.db3`` files and ROS 1 ``.bag``
files through rosbags' ``AnyReader``; types come from the definitions stored in the bag, with the
ROS 2 Jazzy typestore as fallback. A failure to open is a ``BagError`` with what to do about it.
"""

from __future__ import annotations

import stat
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Any

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Ros1ReaderError
from rosbags.rosbag2 import ReaderError as Ros2ReaderError
from rosbags.typesys import Stores, get_typestore

from pair_vpr_ros.errors import BagError

BAG_SUFFIXES = (".mcap", ".db3", ".bag")

_SPECIAL_FILES = (
    (stat.S_ISFIFO, "named pipe (FIFO)"),
    (stat.S_ISSOCK, "socket"),
    (stat.S_ISCHR, "character device"),
    (stat.S_ISBLK, "block device"),
    (stat.S_ISDIR, "folder"),
)
_METADATA_HINT = "the bag folder's metadata.yaml is damaged; `ros2 bag reindex` can rebuild it"
_OPEN_HINTS = {  # first match wins
    "File end magic is invalid": "the MCAP file is truncated or was never closed (recording "
    "interrupted?); the MCAP CLI's `mcap recover` can rebuild it",
    "File magic is invalid": "the file is not an MCAP / ROS 1 bag",
    "seems to be empty": "the file is empty",
    "files are missing": "a storage file that metadata.yaml lists is missing: copy the whole "
    "bag folder",
    "metadata": _METADATA_HINT,
    "YAML": _METADATA_HINT,
    "database": "the sqlite3 (.db3) file is corrupt, truncated or not a rosbag2 database",
    "Bag index looks damaged": "the ROS 1 bag is truncated or was never closed; `rosbag "
    "reindex` can rebuild its index",
    "Bag version": "not a ROS 1 bag (version 2.0)",
    "Rosbag2 version": "written by a rosbag2 newer than this rosbags release reads: upgrade "
    "rosbags (pip install -U rosbags)",
}


def _open_hint(text: str, path: Path) -> str:
    """What to do about an open failure whose message is `text`."""
    hint = next((h for key, h in _OPEN_HINTS.items() if key in text), None)
    if hint is None and "codec can't decode" in text:  # binary where text was expected
        hint = _METADATA_HINT if path.is_dir() else "the file is not a bag"
    return hint or "not a readable bag"


@lru_cache(maxsize=1)
def jazzy_typestore() -> Any:
    """The ROS 2 Jazzy typestore (fallback definitions and the types this package writes)."""
    return get_typestore(Stores.ROS2_JAZZY)


def _check_regular(path: Path) -> None:
    """A FIFO, socket or device named like a bag would block the reader (or never end)."""
    if path.exists() and not path.is_file():
        mode = path.stat().st_mode
        kind = next((name for test, name in _SPECIAL_FILES if test(mode)), "not a regular file")
        raise BagError(
            f"{path} is a {kind}, not a regular file: reading it could block forever; copy the "
            "recording to a file (or rosbag2 folder) first"
        )


def _resolve(path: Path) -> Path:
    """Check ``path`` names something rosbags can open; a folder without metadata.yaml holding one
    storage file is read through that file."""
    if not path.exists():
        raise BagError(
            f"bag {path} does not exist: give a rosbag2 folder, a .mcap or .db3 file "
            "or a ROS 1 .bag"
        )
    if path.is_dir():
        storage = sorted(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
        for part in [path / "metadata.yaml", *storage]:
            _check_regular(part)
        if (path / "metadata.yaml").exists():
            return path
        if len(storage) == 1:
            return storage[0]
        raise BagError(
            f"{path} is a folder without metadata.yaml and with {len(storage)} .mcap/.db3 files: "
            "give a rosbag2 folder or one storage file"
        )
    _check_regular(path)
    if path.suffix not in BAG_SUFFIXES:
        raise BagError(
            f"{path} is not a bag: expected a rosbag2 folder or a file ending in "
            f"{', '.join(BAG_SUFFIXES)}"
        )
    return path


@contextmanager
def open_bag(path: str | Path) -> Iterator[AnyReader]:
    """Open a bag for reading; any failure to open it is a ``BagError`` with a hint."""
    resolved = _resolve(Path(path))
    try:
        reader = AnyReader([resolved], default_typestore=jazzy_typestore())
        reader.open()
    except (AnyReaderError, Ros1ReaderError, Ros2ReaderError, OSError, ValueError) as err:
        text = " ".join(str(err).split()) or type(err).__name__  # one line (YAML errors)
        raise BagError(f"cannot open bag {path}: {text} ({_open_hint(text, resolved)})") from err
    try:
        yield reader
    finally:
        reader.close()


def check_bag_path(path: str | Path) -> Path:
    """The storage path of bag ``path``, or BagError (what is wrong, what to give) when it is
    none; cheap, so a tool checks it before slow work such as finding and loading weights."""
    return _resolve(Path(path))
