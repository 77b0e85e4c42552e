"""Append-only file of per-keyframe dense tokens [N, D], stored with a codec (dense_codec.py).

Entry i lives at byte i * entry_bytes and is never rewritten, so a saved map can share the file
with the live map: the saved keyframe rows say how many entries are valid, later bytes are
ignored (and overwritten by the next append after a crash). Each entry's CRC32 is kept at add
time (in the keyframe store) and checked when the entry is read from disk, so a flipped bit gives
a MapError instead of wrong tokens.
Reads are one `os.pread` per entry, sized to it: a memory map's read-ahead read 4-10x more than a
top-5 fetch needs on a cold cache (issue 34).
Not detected: damage to an entry while verification is off, or to entries already in the LRU.
"""

from __future__ import annotations

import mmap
import os
import struct
import zlib
from array import array
from collections import OrderedDict
from pathlib import Path

import faiss
import numpy as np
from tqdm import tqdm

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map.dense_codec import decode, encode, entry_bytes
from pair_vpr_ros.place_map.files import copy_prefix

DTYPE = np.float16


class DenseStore:
    """Entries [N, D] (float16 when read) in one file; `count` of them are valid.

    path: the file (created when missing if writable).
    crcs: CRC32 of each valid entry (loaded maps), or None for a new, empty store.
    cache_size: hot entries kept in memory (LRU); 0 disables the cache.
    verify_reads: check the CRC32 of every entry read from the file.
    owned: the file belongs to this store alone (no saved manifest names it): may be moved/deleted.
    codec: how entries are stored ("q4" or "f16", dense_codec.py).
    """

    def __init__(
        self,
        path: Path,
        shape: tuple[int, int],
        crcs: array | None = None,
        *,
        writable: bool = True,
        cache_size: int = 128,
        verify_reads: bool = True,
        owned: bool = False,
        codec: str = "f16",
    ) -> None:
        self.path = Path(path)
        self.shape = (int(shape[0]), int(shape[1]))
        self.codec = codec
        self.entry_bytes = entry_bytes(self.shape, codec)
        self.crcs = crcs if crcs is not None else array("I")
        self.count = len(self.crcs)
        self.writable, self.cache_size, self.verify_reads = writable, cache_size, verify_reads
        self.owned = owned
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self.bytes_read = 0  # from the file (benchmarks: bytes read per query)
        flags = os.O_RDWR | os.O_CREAT if writable else os.O_RDONLY
        try:
            self._fd: int | None = os.open(self.path, flags, 0o644)
        except OSError as err:
            raise MapError(f"cannot open dense token file {self.path}: {err.strerror}") from err
        size = os.fstat(self._fd).st_size
        if size < self.count * self.entry_bytes:
            self.close()
            raise MapError(
                f"dense token file {self.path} is too short: {size} bytes hold "
                f"{size // self.entry_bytes} keyframes, the manifest lists {self.count}; the map "
                "is damaged (truncated copy?): restore it from a backup or rebuild it"
            )
        # Bytes past `count` (unsaved or torn appends) are left alone: later appends overwrite
        # them. Never shrinking the file means a manifest that disagrees with it (a hand-edited
        # dense_shape) can not destroy saved tokens; the spot check below reports it instead.
        self._spot_check()

    def _spot_check(self) -> None:
        """The first and last valid entries match their CRC32: the file holds `count` entries
        of `shape` (a wrong shape puts the entry boundaries elsewhere)."""
        for i in sorted({0, self.count - 1} if self.count else set()):
            data = os.pread(self._fd, self.entry_bytes, i * self.entry_bytes)
            if zlib.crc32(data) != self.crcs[i]:
                self.close()
                raise MapError(
                    f"dense token file {self.path} does not match its manifest: keyframe {i} "
                    f"fails its CRC32 check when read as [{self.shape[0]}, {self.shape[1]}] "
                    f"{self.codec} tokens (dense_shape edited, or the file damaged or from "
                    "another map); nothing was changed: restore the map from a backup or "
                    "rebuild it"
                )

    def append(self, dense: np.ndarray) -> int:
        """dense [N, D] float16 C-contiguous (validated by the caller) -> its entry index."""
        assert self._fd is not None and self.writable and dense.dtype == DTYPE
        data = encode(dense, self.codec)
        offset = self.count * self.entry_bytes
        try:
            written = os.pwrite(self._fd, data, offset)
        except OSError as err:
            raise MapError(f"writing dense tokens to {self.path} failed: {err.strerror}") from err
        if written != len(data):
            raise MapError(f"writing dense tokens to {self.path} stopped early: disk full?")
        self.crcs.append(zlib.crc32(data))
        self.count += 1
        return self.count - 1

    def drop_last(self) -> None:
        """Undo the last append (its bytes become an ignored tail)."""
        self.crcs.pop()
        self.count -= 1
        self._cache.pop(self.count, None)

    def truncate(self, count: int) -> None:
        """Forget entries >= count (their bytes become an ignored tail)."""
        while self.count > count:
            self.drop_last()

    def read(self, ids: np.ndarray) -> np.ndarray:
        """ids [K] valid entry indices -> [K, N, D] float16 (a copy)."""
        out = np.empty((len(ids), *self.shape), DTYPE)
        for row, i in enumerate(ids):
            out[row] = self._entry(int(i))
        return out

    def _entry(self, i: int) -> np.ndarray:
        hit = self._cache.get(i)
        if hit is not None:
            self._cache.move_to_end(i)
            return hit
        buf = os.pread(self._fd, self.entry_bytes, i * self.entry_bytes)
        self.bytes_read += len(buf)
        if len(buf) != self.entry_bytes or (self.verify_reads and zlib.crc32(buf) != self.crcs[i]):
            raise self._corrupt(i)
        entry = decode(buf, self.shape, self.codec)
        if self.cache_size > 0:
            self._cache[i] = entry
            if len(self._cache) > self.cache_size:
                self._cache.popitem(last=False)
        return entry

    def _corrupt(self, i: int) -> MapError:
        return MapError(
            f"dense tokens of keyframe {i} in {self.path} fail their CRC32 check: the file is "
            "damaged on disk; restore the map from a backup or rebuild it"
        )

    def verify_all(self) -> None:
        """Check every entry's CRC32 (reads the whole file)."""
        step = max(1, (64 << 20) // self.entry_bytes)
        starts = range(0, self.count, step)
        for start in tqdm(starts, desc="verify dense", disable=self.count < 5000):
            stop = min(start + step, self.count)
            data = os.pread(self._fd, (stop - start) * self.entry_bytes, start * self.entry_bytes)
            for i in range(start, stop):
                lo = (i - start) * self.entry_bytes
                if zlib.crc32(data[lo : lo + self.entry_bytes]) != self.crcs[i]:
                    raise self._corrupt(i)

    def crc_bytes(self) -> bytes:
        """The CRC32 of each valid entry as little-endian uint32 [count]."""
        return np.frombuffer(self.crcs, dtype=np.uint32).astype("<u4").tobytes()

    def sync(self) -> None:
        """Make the valid entries durable."""
        os.fsync(self._fd)

    def copy_to(self, dst: Path) -> None:
        """Write the valid entries to a new file `dst` (fsynced)."""
        copy_prefix(self._fd, dst, self.count * self.entry_bytes)

    def close(self) -> None:
        self._cache.clear()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self) -> None:
        if getattr(self, "_fd", None) is not None:
            self.close()


def read_crcs(path: Path, count: int) -> array:
    """Read a file written from `DenseStore.crc_bytes`; -> array of `count` CRC32 values."""
    data = path.read_bytes()
    if len(data) != 4 * count:
        raise MapError(
            f"dense checksum file {path} holds {len(data) // 4} entries, the manifest lists "
            f"{count}: the map is damaged, restore it from a backup or rebuild it"
        )
    crcs = array("I")
    crcs.frombytes(np.frombuffer(data, dtype="<u4").astype(np.uint32).tobytes())
    return crcs


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
