"""Durable file operations for map directories: fsync, atomic publish, a writer lock.

A save is crash-safe only if every new file is on disk before the manifest that names it, and the
manifest switch itself is one `os.replace`; these helpers give those guarantees on POSIX.
"""

from __future__ import annotations

import errno
import fcntl
import os
import zlib
from collections.abc import Callable
from pathlib import Path

from pair_vpr_ros.errors import MapError

LOCK_NAME = "map.lock"
TMP_SUFFIX = ".tmp"
_COPY_CHUNK = 64 << 20


def fsync_path(path: Path) -> None:
    """Flush a file's (or a directory's entries') data to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def publish(directory: Path, name: str, write: Callable[[Path], None]) -> Path:
    """Write `directory/name` via `write(tmp_path)`, fsync it, then rename it into place.

    A failure removes the `*.tmp` file again; a crash leaves at most a stray one (removed by
    the next save), never a half-written `name`.
    """
    final = directory / name
    tmp = directory / (name + TMP_SUFFIX)
    try:
        write(tmp)
        fsync_path(tmp)
        os.replace(tmp, final)
    except BaseException:
        remove_quietly(tmp)  # a failed write (disk full) must not keep its space
        raise
    return final


def remove_quietly(path: Path) -> None:
    """Delete `path` if it exists; a failure to do so is not worth reporting over the caller's."""
    try:
        os.remove(path)
    except OSError:
        pass


def write_bytes_durably(path: Path, data: bytes) -> None:
    """Write `data` to `path` and fsync it (a partial file is left on failure)."""
    with open(path, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


def copy_prefix(src_fd: int, dst: Path, nbytes: int) -> None:
    """Copy the first `nbytes` of an open file to a new file `dst` (kernel-side where possible)."""
    with open(dst, "wb") as out:
        done = 0
        while done < nbytes:
            step = min(_COPY_CHUNK, nbytes - done)
            try:
                n = os.copy_file_range(src_fd, out.fileno(), step, done, done)
            except OSError as err:
                if err.errno not in (errno.EXDEV, errno.ENOSYS, errno.EOPNOTSUPP, errno.EINVAL):
                    raise
                n = out.write(os.pread(src_fd, step, done))
            if n <= 0:
                raise MapError(f"copying dense tokens to {dst} stopped at byte {done}: disk full?")
            done += n
        out.flush()
        os.fsync(out.fileno())


def crc32_file(path: Path) -> int:
    """CRC32 of a whole file, read in chunks."""
    crc = 0
    with open(path, "rb") as fh:
        while chunk := fh.read(_COPY_CHUNK):
            crc = zlib.crc32(chunk, crc)
    return crc


def same_device(a: Path, b: Path) -> bool:
    return os.stat(a).st_dev == os.stat(b).st_dev


class DirLock:
    """Exclusive advisory lock (`flock`) marking the one PlaceMap that may write a map directory.

    Released by `release()` or when the process dies (also on `kill -9`), so it never goes stale.
    """

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        path = directory / LOCK_NAME
        try:
            self._fd: int | None = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise MapError(
                f"cannot create the lock file {path} ({err.strerror}): a map that may not be "
                "written to can still be loaded with read_only=True"
            ) from err
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            holder = os.pread(self._fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(self._fd)
            self._fd = None
            raise MapError(
                f"map directory {directory} is open for writing by another PlaceMap "
                f"(pid {holder}); close that one first, or load this map with read_only=True"
            ) from err
        try:
            os.ftruncate(self._fd, 0)
            os.pwrite(self._fd, f"{os.getpid()}\n".encode(), 0)
        except OSError as err:  # a full disk: the pid does not fit
            self.release()
            raise MapError(
                f"cannot write the lock file {path} ({err.strerror}): free disk space or pick "
                "another directory and retry"
            ) from err

    def release(self) -> None:
        if getattr(self, "_fd", None) is not None:
            os.close(self._fd)  # closing drops the flock
            self._fd = None

    def __del__(self) -> None:  # a PlaceMap dropped without close() still unlocks
        self.release()
