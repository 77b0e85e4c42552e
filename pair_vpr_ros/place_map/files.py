"""Durable file operations for map directories: fsync, atomic publish, a writer lock, and the
flat map's descriptor cache (below).

A save is crash-safe only if every new file is on disk before the manifest that names it, and the
manifest switch itself is one `os.replace`; these helpers give those guarantees on POSIX.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os
import struct
import zlib
from collections.abc import Callable
from pathlib import Path

import faiss
import numpy as np

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


# ---------------------------------------------------------------------------- descriptor cache
# A flat map's descriptors, next to its keyframe store (`map-<g>.sqlite.desc`), so a load reads
# neither every row nor every byte: the store's rows stay the saved truth; the cache is derived
# from them, written after each save, and used only when its header names exactly the store's
# keyframe count and its rows match the CRC32 in that header (otherwise the load scans the rows
# as before, and the next save writes the cache again). Layout: a 4096-byte header page
# (magic, version, dim, count, CRC32 of the rows), then the rows [count, dim] float32, so the
# page's last bytes can take FAISS's own IndexFlatIP header in a private memory map and FAISS
# searches the rows where the page cache holds them (no copy at load).
CACHE_SUFFIX = ".desc"
_CACHE_HEAD = struct.Struct("<4sIIQI")  # b"PVDC", version 1, dim, count, crc32 of the rows
_PAGE = 4096
_FAISS_HEAD = struct.Struct("<4siqqqBiq")  # faiss IndexFlatIP: fourcc, d, ntotal, 2 dummies,
# is_trained, metric (0: inner product), then the float vector's size and its values


def cache_path(store_path: Path) -> Path:
    return store_path.with_name(store_path.name + CACHE_SUFFIX)


class CacheCheck:
    """The CRC32 check of a mapped cache's rows, made when the rows are first used (`ok`), not
    at load: a load then costs the same at any size (a thread started at load measured no
    better on 2 busy cores: starting it waited tens of ms for a core)."""

    def __init__(self, rows: memoryview, crc: int) -> None:
        self._rows, self._crc = rows, crc

    def ok(self) -> bool:
        return zlib.crc32(self._rows) == self._crc


def open_cache(path: Path, dim: int, count: int) -> tuple[faiss.Index, object, int] | None:
    """-> (an IndexFlatIP of the `count` cached descriptors [count, dim] that views the file,
    (what must stay alive while it is used, its `CacheCheck`), the rows' CRC32), or None when
    the cache cannot hold those rows (missing, short, another count or dim). The index must not
    be used before `CacheCheck.ok` says the rows match their CRC32."""
    try:
        with open(path, "rb") as fh:
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_COPY)
    except (OSError, ValueError):
        return None
    size = _PAGE + count * 4 * dim
    if count < 1 or len(mm) < size:
        return None
    magic, version, d, n, crc = _CACHE_HEAD.unpack_from(mm)
    if (magic, version, d, n) != (b"PVDC", 1, dim, count):
        return None
    check = CacheCheck(memoryview(mm)[_PAGE:size], crc)
    start = _PAGE - _FAISS_HEAD.size
    mm[start:_PAGE] = _FAISS_HEAD.pack(b"IxFI", dim, count, 1 << 20, 1 << 20, 1, 0, count * dim)
    view = np.frombuffer(mm, np.uint8, size - start, start)  # private: the file is unchanged
    index = faiss.read_index(faiss.ZeroCopyIOReader(faiss.swig_ptr(view), view.size))
    return index, (mm, view, check), crc


def write_cache(path: Path, rows: np.ndarray, start: int, crc: int) -> int:
    """Write descriptors rows [m, dim] float32 as entries start.. of the cache (start 0: a new
    cache) -> the CRC32 of its rows 0..start+m-1 (`crc`: that of rows 0..start-1). Not
    fsynced: the cache is checked at every load and rebuilt when it does not match."""
    rows = np.ascontiguousarray(rows, "<f4")
    data = rows.tobytes()
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        if start == 0:
            os.ftruncate(fd, 0)
        os.pwrite(fd, data, _PAGE + start * rows.shape[1] * 4)
        crc = zlib.crc32(data, crc if start else 0)
        os.pwrite(fd, _CACHE_HEAD.pack(b"PVDC", 1, rows.shape[1], start + len(rows), crc), 0)
    finally:
        os.close(fd)
    return crc
