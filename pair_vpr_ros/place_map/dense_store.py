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

import os
import zlib
from array import array
from collections import OrderedDict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map.dense_codec import (
    BASIS_FROM,
    Basis,
    decode,
    encode,
    entry_bytes,
    head_bytes,
)
from pair_vpr_ros.place_map.files import copy_prefix

DTYPE = np.float16


class DenseStore:
    """Entries [N, D] (float16 when read) in one file; `count` of them are valid.

    path: the file (created when missing if writable).
    crcs: CRC32 of each valid entry (loaded maps), or None for a new, empty store.
    cache_size: hot entries kept in memory (LRU); 0 disables the cache.
    verify_reads: check the CRC32 of every entry read from the file.
    owned: the file belongs to this store alone (no saved manifest names it): may be moved/deleted.
    codec: how entries are stored ("q4", "p4", "q4a" or "f16", dense_codec.py).
    weight: p4: the pair decoder's first layer W [C, D] its basis is fitted for (None: the
        tokens' own channels); decoding never needs it.
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
        weight: np.ndarray | None = None,
    ) -> None:
        self.path = Path(path)
        self.shape = (int(shape[0]), int(shape[1]))
        self.codec, self.weight = codec, weight
        self.entry_bytes = entry_bytes(self.shape, codec)
        self.head = head_bytes(self.shape, codec)  # p4: its basis, before entry 0
        self.basis: Basis | None = None
        # p4, a new store: the float16 tokens of the entries before the basis, to fit it on
        # and to code them with it too (Basis.recoded)
        self._first: list[np.ndarray] | None = [] if codec == "p4" and crcs is None else None
        self.crcs = crcs if crcs is not None else array("I")
        self.count = len(self.crcs)
        self.writable, self.cache_size, self.verify_reads = writable, cache_size, verify_reads
        self.owned = owned
        self._cache: OrderedDict[int, np.ndarray] = OrderedDict()
        self.bytes_read = 0  # from the file (benchmarks: bytes read per query)
        self.copied_crcs: array | None = None  # of the last `copy_to` that re-coded entries
        flags = os.O_RDWR | os.O_CREAT if writable else os.O_RDONLY
        try:
            self._fd: int | None = os.open(self.path, flags, 0o644)
        except OSError as err:
            raise MapError(f"cannot open dense token file {self.path}: {err.strerror}") from err
        size = os.fstat(self._fd).st_size
        if self.count and size < self.head + self.count * self.entry_bytes:
            self.close()
            raise MapError(
                f"dense token file {self.path} is too short: {size} bytes hold "
                f"{max(size - self.head, 0) // self.entry_bytes} keyframes, the manifest lists "
                f"{self.count}; the map is damaged (truncated copy?): restore it from a backup "
                "or rebuild it"
            )
        if self.head and size >= self.head:  # shorter: a new file (written at entry 0)
            self._open_basis()
        # Bytes past `count` (unsaved or torn appends) are left alone: later appends overwrite
        # them. Never shrinking the file means a manifest that disagrees with it (a hand-edited
        # dense_shape) can not destroy saved tokens; the spot check below reports it instead.
        self._spot_check()

    def _spot_check(self) -> None:
        """The first and last valid entries match their CRC32: the file holds `count` entries
        of `shape` (a wrong shape puts the entry boundaries elsewhere)."""
        for i in sorted({0, self.count - 1} if self.count else set()):
            data = os.pread(self._fd, self.entry_bytes, self._at(i))
            if not self._intact(data, i):
                self.close()
                raise MapError(
                    f"dense token file {self.path} does not match its manifest: keyframe {i} "
                    f"fails its CRC32 check when read as [{self.shape[0]}, {self.shape[1]}] "
                    f"{self.codec} tokens (dense_shape edited, or the file damaged or from "
                    "another map); nothing was changed: restore the map from a backup or "
                    "rebuild it"
                )

    def _at(self, i: int) -> int:
        return self.head + i * self.entry_bytes

    def _crc(self, data: bytes, i: int) -> int:
        """CRC32 of entry i's bytes; p4 entries coded with the basis: seeded with its CRC32."""
        coded = self.basis is not None and i >= self.basis.start
        return zlib.crc32(data, self.basis.crc if coded else 0)

    def _intact(self, data: bytes, i: int) -> bool:
        """Entry i's bytes match their CRC32 (the basis's for entries it re-coded in place)."""
        if self.basis is not None and i < len(self.basis.recoded):
            return zlib.crc32(data) == self.basis.recoded[i]
        return self._crc(data, i) == self.crcs[i]

    def _open_basis(self) -> None:
        """p4: read the basis from the file's head; MapError when the valid entries need one
        and it is missing or damaged. Up to BASIS_FROM entries a damaged head may be one torn
        past the save (fitted again at the next append): the entries' CRC32s, seeded with the
        basis they were coded with, tell (`_spot_check`)."""
        data = os.pread(self._fd, self.head, 0)
        try:
            basis = Basis.from_bytes(data, self.shape, str(self.path))
        except MapError:
            if self.count > BASIS_FROM:
                self.close()
                raise
            basis = None
        if basis is None and self.count > BASIS_FROM:
            self.close()
            raise MapError(
                f"the p4 basis at the head of {self.path} is missing (zeros) but keyframes "
                f"{BASIS_FROM}.. need it: the file is damaged; restore the map from a backup or "
                "rebuild it"
            )
        if basis is not None and (self.count > basis.start or basis.recoded):
            self.basis = basis

    def adopt(self, basis: Basis) -> None:
        """Code every entry with `basis` (another map's, e.g. a merge's first map), from the
        first; only while the store is empty."""
        assert self.codec == "p4" and self.count == 0
        self._write_basis(Basis(basis.mean, basis.enc16, basis.bits, 0))

    def _write_basis(self, basis: Basis) -> None:
        """Write the basis into the head (once per map: fsynced with the entries by `sync`,
        before any saved row names an entry coded with it)."""
        self._write(basis.to_bytes(), 0, "the p4 basis")
        self.basis = basis

    def _write(self, data: bytes, offset: int, what: str) -> None:
        try:
            written = os.pwrite(self._fd, data, offset)
        except OSError as err:
            raise MapError(f"writing {what} to {self.path} failed: {err.strerror}") from err
        if written != len(data):
            raise MapError(f"writing {what} to {self.path} stopped early: disk full?")

    def _encode_q4(self, dense: np.ndarray) -> bytes:
        data = encode(dense, "q4")  # tiny shapes: p4's entries are longer than q4's
        return data + bytes(self.entry_bytes - len(data))

    def _encode(self, dense: np.ndarray) -> bytes:
        if self.codec != "p4":
            return encode(dense, self.codec)
        if self.basis is None and self.count >= BASIS_FROM:
            self._fit()
        if self.basis is None or self.count < self.basis.start:
            return self._encode_q4(dense)
        return self.basis.encode(dense, self.entry_bytes)

    def _fit(self) -> None:
        """Fit the basis on the first BASIS_FROM entries (their float16 tokens when this store
        saw them added, else as decoded) and write it; in a file no save names yet, code those
        entries with it too, in their slots (their q4 form is then needed by no one)."""
        first = self._first if self._first and len(self._first) == BASIS_FROM else None
        tokens = np.stack(first) if first else self.read(np.arange(BASIS_FROM))
        size, n = self.entry_bytes, self.shape[0]
        basis = Basis.fit(tokens.reshape(-1, self.shape[1]), n, size, BASIS_FROM, self.weight)
        if not (first and self.owned):  # a save names the file: its entries stay as they are
            self._write_basis(basis)
            self._first = first  # their float16 tokens: the next save's copy re-codes them
            return
        coded = [basis.encode(t, size) for t in first]
        crcs = [zlib.crc32(c) for c in coded]
        self._write_basis(Basis(basis.mean, basis.enc16, basis.bits, basis.start, crcs))
        try:  # the head first (it may need new blocks), then the slots (they have theirs)
            for i, data in enumerate(coded):
                self._write(data, self._at(i), "dense tokens")
        except MapError:  # put the q4 forms back: the map goes on without re-coded entries
            for i, t in enumerate(first):
                self._write(self._encode_q4(t), self._at(i), "dense tokens")
            self._write_basis(basis)
            raise
        self._first = None
        self._cache.clear()  # entries 0.. decode with the basis now

    def _decode(self, data: bytes, i: int) -> np.ndarray:
        if self.codec != "p4":
            return decode(data, self.shape, self.codec)
        if self.basis is None or len(self.basis.recoded) <= i < self.basis.start:
            return decode(data[: entry_bytes(self.shape, "q4")], self.shape, "q4")
        return self.basis.decode(data, self.shape[0])

    def append(self, dense: np.ndarray) -> int:
        """dense [N, D] float16 C-contiguous (validated by the caller) -> its entry index."""
        assert self._fd is not None and self.writable and dense.dtype == DTYPE
        data = self._encode(dense)
        self._write(data, self._at(self.count), "dense tokens")
        self.crcs.append(self._crc(data, self.count))
        self.count += 1
        if self._first is not None and self.basis is None:
            self._first.append(dense.copy())
        return self.count - 1

    def drop_last(self) -> None:
        """Undo the last append (its bytes become an ignored tail)."""
        self.crcs.pop()
        self.count -= 1
        self._cache.pop(self.count, None)
        if self._first is not None and len(self._first) > self.count:
            self._first.pop()

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
        buf = os.pread(self._fd, self.entry_bytes, self._at(i))
        self.bytes_read += len(buf)
        bad = self.verify_reads and not self._intact(buf, i)
        if len(buf) != self.entry_bytes or bad:
            raise self._corrupt(i)
        entry = self._decode(buf, i)
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
            data = os.pread(self._fd, (stop - start) * self.entry_bytes, self._at(start))
            for i in range(start, stop):
                lo = (i - start) * self.entry_bytes
                if not self._intact(data[lo : lo + self.entry_bytes], i):
                    raise self._corrupt(i)

    def sync(self) -> None:
        """Make the valid entries durable."""
        os.fsync(self._fd)

    @property
    def recode_pending(self) -> bool:
        """p4: a basis fitted in a file a save named, while this store still holds the float16
        tokens of the first entries (coded q4 before it): the next save writes a new
        generation whose copy (`copy_to`) codes them with the basis too."""
        first, basis = self._first, self.basis
        if not first or basis is None:
            return False
        return not basis.recoded and len(first) == basis.start

    def copy_to(self, dst: Path) -> None:
        """Write the valid entries to a new file `dst` (fsynced). `recode_pending`: the first
        entries coded with the basis, whose head then lists their CRC32s; that changes the
        basis's CRC32, which seeds those of the later entries: `copied_crcs` are then the
        CRC32s of the copy's entries, for its keyframe rows."""
        self.copied_crcs = None
        if not self.recode_pending:
            copy_prefix(self._fd, dst, self._at(self.count))
            return
        old, size = self.basis, self.entry_bytes
        coded = [old.encode(t, size) for t in self._first]
        new = Basis(old.mean, old.enc16, old.bits, old.start, [zlib.crc32(c) for c in coded])
        crcs = array("I", self.crcs[: len(coded)])  # theirs: the head's list is checked
        with open(dst, "wb") as out:
            out.write(new.to_bytes().ljust(self.head, b"\0") + b"".join(coded))
            for i in range(len(coded), self.count):  # the same bytes, CRC32s seeded anew
                data = os.pread(self._fd, size, self._at(i))
                if not self._intact(data, i):
                    raise self._corrupt(i)
                crcs.append(zlib.crc32(data, new.crc))
                out.write(data)
            out.flush()
            os.fsync(out.fileno())
        self.copied_crcs = crcs

    def close(self) -> None:
        self._cache.clear()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __del__(self) -> None:
        if getattr(self, "_fd", None) is not None:
            self.close()
