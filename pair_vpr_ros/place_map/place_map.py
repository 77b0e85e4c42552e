"""PlaceMap: the keyframe map (global descriptors, dense tokens, metadata) with atomic save/load.

Keyframe ids are 0, 1, 2, ... in insertion order and survive save/load, so a loaded map continues
mapping where it stopped (multi-session). The live map works on private copies in a temporary
folder, except for the append-only dense file, which it shares with the save it came from:
entries past the saved count are invisible to that save. So a saved map changes only when `save`
commits (see persist.py), and `save` never rewrites dense entries that are already on disk.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import tempfile
import weakref
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.errors import ConfigError, MapError, MapFingerprintError
from pair_vpr_ros.identity import DEFAULT_ROBOT, LEGACY_SESSION
from pair_vpr_ros.place_map import persist
from pair_vpr_ros.place_map.checks import dense_tokens, keyframe_ids, unit_descriptor
from pair_vpr_ros.place_map.dense_store import DenseStore, entry_bytes
from pair_vpr_ros.place_map.files import LOCK_NAME, DirLock, fsync_path
from pair_vpr_ros.place_map.index import IndexConfig, make_index
from pair_vpr_ros.place_map.manifest import MANIFEST_NAME, Manifest, read_manifest, remove_stale
from pair_vpr_ros.place_map.metadata import KeyframeMeta, MetadataStore, validate_meta
from pair_vpr_ros.place_map.milvus_expr import Exclusion, identity, utc_session


class PlaceMap:
    """Keyframe map: FAISS index of [desc_dim] descriptors, [N, D] float16 dense tokens, metadata.

    desc_dim: global descriptor size (512). dense_shape: (N, D) tokens per keyframe.
    fingerprint: opaque model identity (checkpoint hash + input size + desc dim), stored on save.
    index: "flat" (exact) | "ivf" (exact below 25,000 keyframes, then k-means lists: ~1e6
        keyframes; training pauses an add, see place_map/ivf.py) | "hnsw" | an IndexConfig
        (kind "milvus": a Milvus collection, see place_map/milvus.py and docs/milvus.md).
    dense_cache_size: dense entries kept in memory (LRU). verify_dense_reads: CRC32-check
    entries read from disk. work_dir: parent of the temporary working folder (default: $TMPDIR);
    put it on the disk of the map directory so the first save moves the dense file, not copies it.
    """

    def __init__(
        self,
        desc_dim: int = 512,
        dense_shape: tuple[int, int] = (529, 768),
        fingerprint: str = "",
        index: str | IndexConfig = "flat",
        *,
        dense_cache_size: int = 128,
        verify_dense_reads: bool = True,
        work_dir: str | os.PathLike | None = None,
    ) -> None:
        config = index if isinstance(index, IndexConfig) else IndexConfig(kind=index)
        if int(desc_dim) < 1 or len(dense_shape) != 2 or min(dense_shape) < 1:
            raise ConfigError(f"bad place map shape: desc_dim={desc_dim}, dense={dense_shape}")
        self._setup(dense_cache_size, verify_dense_reads, work_dir)
        self.desc_dim = int(desc_dim)
        self.dense_shape = (int(dense_shape[0]), int(dense_shape[1]))
        self.fingerprint = str(fingerprint)
        self._meta = MetadataStore(self._tmp / "meta.sqlite")
        self._dense = self._fresh_dense()
        try:
            self._index = make_index(self.desc_dim, config, self.fingerprint)
        except BaseException:
            self.close()
            raise

    def _setup(self, cache_size: int, verify_reads: bool, work_dir) -> None:
        self._cache_size, self._verify_reads = int(cache_size), bool(verify_reads)
        self._index: Any = None  # DescriptorIndex (FAISS) or MilvusIndex
        self._meta: MetadataStore | None = None
        self._dense: DenseStore | None = None
        self._home: Path | None = None  # directory of the last load/save (we hold its lock)
        self._lock: DirLock | None = None
        self._dense_committed = False  # the dense file is the one `_home`'s manifest names
        self._read_only = False
        self.load_note = ""  # what a caller should log about the load ("" = nothing)
        self._fresh_count = 0
        self._closed = False
        self.session = utc_session()  # of keyframes that name none (see `identity`)
        try:
            self._tmp = Path(tempfile.mkdtemp(prefix="pairvpr-map-", dir=work_dir))
        except OSError as err:
            raise MapError(f"cannot create a working folder in {work_dir}: {err}") from err
        self._remove_tmp = weakref.finalize(self, shutil.rmtree, self._tmp, True)

    def _fresh_dense(self) -> DenseStore:
        self._fresh_count += 1
        path = self._tmp / f"dense-work-{self._fresh_count}.f16"
        reads = dict(cache_size=self._cache_size, verify_reads=self._verify_reads)
        return DenseStore(path, self.dense_shape, owned=True, **reads)

    # ----------------------------------------------------------------- mapping and queries

    def add(
        self, desc: np.ndarray, dense: np.ndarray, meta: KeyframeMeta, features: bytes = b""
    ) -> int:
        """desc [desc_dim] (normalised here), dense [N, D] float (stored float16), packed
        features (b"": none) -> new id."""
        self._check_writable("add to")
        query = unit_descriptor(desc, self.desc_dim)
        tokens = dense_tokens(dense, self.dense_shape)
        meta = validate_meta(meta)
        kf_id = len(self)
        self._dense.append(tokens)
        try:
            self._meta.add(replace(meta, id=kf_id), bytes(features))
            self._index.add(query[None], [(*self.identity(meta), meta.stamp)])
        except BaseException as err:
            self._meta.delete_from(kf_id)
            self._dense.drop_last()
            if isinstance(err, sqlite3.Error):
                raise MapError(f"storing metadata of keyframe {kf_id} failed: {err}") from err
            raise
        return kf_id

    def search(
        self,
        desc: np.ndarray,
        k: int,
        max_id: int | None = None,
        allowed: np.ndarray | None = None,
        exclude: tuple[int, int] | None = None,
        exclusion: Exclusion | None = None,
    ) -> list[tuple[int, float]]:
        """desc [desc_dim] -> up to k (id, inner-product similarity), best first, id <= max_id
        and, with `allowed` (bool [m]), only ids i < m with allowed[i]; with `exclude`
        (lo, hi) alone, no id in lo..hi-1; `exclusion` (kind "milvus" only:
        `filters_in_index`) applies the temporal and robot/session rules as a filter in the
        index. MapUnavailableError: the index server did not answer."""
        self._check_open()
        if int(k) < 0:
            raise MapError(f"search k must be >= 0, got {k}")
        query = unit_descriptor(desc, self.desc_dim)
        ids, sims = self._index.search(query, int(k), max_id, allowed, exclude, exclusion)
        return [(int(i), float(s)) for i, s in zip(ids, sims, strict=True)]

    def get_dense(self, ids: Iterable[int]) -> np.ndarray:
        """ids [K] -> dense tokens [K, N, D] float16."""
        return self._dense.read(keyframe_ids(ids, len(self)))

    def get_desc(self, ids: Iterable[int]) -> np.ndarray:
        """ids [K] -> stored (L2-normalised) descriptors [K, desc_dim] float32."""
        return self._index.reconstruct(keyframe_ids(ids, len(self)))

    def meta(self, kf_id: int) -> KeyframeMeta:
        """Metadata of one keyframe; MapError if the id is not in the map."""
        self._check_open()
        found = self._meta.get(kf_id)
        if found is None:
            raise MapError(f"keyframe {kf_id} is not in the map (ids 0..{len(self) - 1})")
        return found

    def features(self, kf_id: int) -> bytes:
        """Packed features of a keyframe (b"": none, e.g. a map saved before features were
        kept); MapError for an unknown id or damaged bytes."""
        self.meta(kf_id)
        return self._meta.features(kf_id)

    def feature_stats(self) -> tuple[int, int]:
        """(keyframes with features, bytes of all their features)."""
        self._check_open()
        return self._meta.feature_stats()

    def all_meta(self) -> list[KeyframeMeta]:
        """Every keyframe's metadata, by id (for plots and markers)."""
        self._check_open()
        return self._meta.all()

    def __len__(self) -> int:
        self._check_open()
        return len(self._index)

    def clear(self) -> None:
        """Forget every keyframe (ids restart at 0); the last save stays as it is until `save`."""
        self._check_writable("clear")
        self._index.reset()
        self._meta.clear()
        old, self._dense = self._dense, self._fresh_dense()
        self._discard(old)
        self._dense_committed = False

    @property
    def index_config(self) -> IndexConfig:
        return self._index.config

    @property
    def filters_in_index(self) -> bool:
        """The index applies `Exclusion`s itself (Milvus filter expressions)."""
        return self._index.config.kind == "milvus"

    def identity(self, item: Any) -> tuple[str, str]:
        """(robot, session) of a keyframe or frame (milvus_expr.identity)."""
        return identity(item, self.session)

    @property
    def index_diagnostics(self) -> dict[str, int]:
        """Kind "milvus": searches skipped and keyframes waiting while it was unreachable."""
        return self._index.diagnostics() if self.filters_in_index else {}

    @property
    def bytes_per_keyframe(self) -> int:
        """Stored bytes of one keyframe: dense tokens + float32 descriptor (metadata aside)."""
        return entry_bytes(self.dense_shape) + 4 * self.desc_dim

    @property
    def directory(self) -> Path | None:
        """The map directory last loaded from or saved to (None for a never-saved map)."""
        return self._home

    # ----------------------------------------------------------------------- save and load

    def save(self, directory: str | os.PathLike, overwrite: bool = False) -> Path:
        """Atomically make `directory` hold this map (created if needed) -> its resolved path.

        A crash at any moment leaves the previous save in `directory` loadable and intact. After
        a save the map continues in that directory: later saves there only append dense tokens.
        A map of another model saved there is refused (MapFingerprintError) unless `overwrite`.
        A failed save into a folder it created leaves no folder behind.
        """
        self._check_writable("save")
        target = Path(directory).expanduser().resolve()
        if target != self._home and not overwrite:
            self._refuse_other_model(target)
        created = not target.exists()
        try:
            target.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise MapError(f"cannot create map directory {target}: {err.strerror}") from err
        try:
            new_lock = DirLock(target) if target != self._home else None
        except MapError:
            if created:
                _remove_new_folder(target)
            raise
        in_place = self._dense_committed and target == self._home
        try:
            manifest, copied = persist.save(target, self._parts(), in_place)
        except BaseException as err:
            if new_lock is not None:
                new_lock.release()
                if created:
                    _remove_new_folder(target)
            if isinstance(err, (OSError, sqlite3.Error, RuntimeError)):  # RuntimeError: FAISS
                raise MapError(
                    f"saving the place map to {target} failed ({err}); the previous save there "
                    "(if any) is unchanged: free disk space or pick another directory and retry"
                ) from err
            raise
        self._after_commit(target, manifest, copied, new_lock)
        return target

    def _refuse_other_model(self, target: Path) -> None:
        if not (target / MANIFEST_NAME).is_file():
            return
        try:
            theirs = read_manifest(target).fingerprint
        except MapError:
            return  # a damaged save: the save replaces it as before
        if self.fingerprint and theirs and theirs != self.fingerprint:
            raise MapFingerprintError(
                f"map directory {target} holds a map of another model (fingerprint {theirs!r}, "
                f"this map's is {self.fingerprint!r}): save into another directory, or pass "
                "overwrite=True to replace it"
            )

    def _parts(self) -> persist.MapParts:
        return persist.MapParts(
            self._index, self._meta, self._dense, self.desc_dim, self.dense_shape, self.fingerprint
        )

    def _after_commit(
        self, d: Path, manifest: Manifest, copied: Path | None, lock: DirLock | None
    ) -> None:
        """Bookkeeping once `d` holds the new save; if it fails, the next save copies again."""
        self._dense_committed = False
        if copied is None:
            self._dense.owned = False  # a save names this file now: never move or delete it
        if lock is not None:
            if self._lock is not None:
                self._lock.release()
            self._lock, self._home = lock, d
        persist.reached("committed")
        try:
            if copied is not None:  # continue in the new copy; the old file stays with its save
                old = self._dense
                self._dense = DenseStore(
                    copied,
                    self.dense_shape,
                    old.crcs,
                    cache_size=self._cache_size,
                    verify_reads=self._verify_reads,
                )
                self._discard(old)
            self._dense_committed = True
            fsync_path(d)  # make the manifest switch durable before deleting what it replaced
        except OSError as err:
            raise MapError(
                f"the place map was saved to {d}, but finishing the save failed ({err}); "
                "save again to make sure it is on disk"
            ) from err
        remove_stale(d, manifest.file_names() | {MANIFEST_NAME, LOCK_NAME})
        persist.reached("cleaned")

    @classmethod
    def load(
        cls,
        directory: str | os.PathLike,
        expected_fingerprint: str | None = None,
        *,
        read_only: bool = False,
        ef_search: int | None = None,
        verify_dense: bool = False,
        dense_cache_size: int = 128,
        verify_dense_reads: bool = True,
        work_dir: str | os.PathLike | None = None,
        legacy_identity: tuple[str, str] = (DEFAULT_ROBOT, LEGACY_SESSION),
    ) -> PlaceMap:
        """Open a saved map to continue mapping (or only to query, with read_only=True).
        legacy_identity: (robot, session) of the keyframes of a format-1 map (`load_note`).

        expected_fingerprint: refuse (MapFingerprintError) a map built by another model.
        ef_search: override the saved HNSW ef_search. verify_dense: CRC-check every dense entry
        now (reads the whole dense file). A writable load locks the directory against other
        writers (read-only loads may share it); the saved copy changes only on the next save.
        """
        d = Path(directory).expanduser().resolve()
        if not (d / MANIFEST_NAME).is_file():
            read_manifest(d)  # raises the MapError that explains what is missing
        obj = cls.__new__(cls)
        obj._setup(dense_cache_size, verify_dense_reads, work_dir)
        try:
            obj._lock = None if read_only else DirLock(d)
            parts = persist.open_saved(
                d,
                expected_fingerprint,
                obj._tmp / "meta.sqlite",
                read_only=read_only,
                ef_search=ef_search,
                cache_size=obj._cache_size,
                verify_reads=obj._verify_reads,
                legacy=legacy_identity,
            )
            obj._index, obj._meta, obj._dense = parts.index, parts.meta, parts.dense
            if verify_dense:
                obj._dense.verify_all()
        except BaseException:
            obj.close()
            raise
        obj.desc_dim, obj.dense_shape = parts.desc_dim, parts.dense_shape
        obj.fingerprint = parts.fingerprint
        obj._home, obj._dense_committed, obj._read_only = d, True, read_only
        obj.load_note = parts.note
        return obj

    # ------------------------------------------------------------------------ life cycle

    def close(self) -> None:
        """Release files, the directory lock and the working folder (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._dense is not None:
            self._discard(self._dense)
        if self._meta is not None:
            self._meta.close()
        if hasattr(self._index, "close"):
            self._index.close()
        if self._lock is not None:
            self._lock.release()
        self._remove_tmp()

    def __enter__(self) -> PlaceMap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        if self._closed:
            return "PlaceMap(closed)"
        return (
            f"PlaceMap({len(self)} keyframes, index={self._index.config.kind!r}, "
            f"dense={self.dense_shape}, directory={self._home})"
        )

    def _discard(self, store: DenseStore) -> None:
        store.close()
        if store.owned:
            store.path.unlink(missing_ok=True)

    def _check_open(self) -> None:
        if self._closed:
            raise MapError("this PlaceMap is closed: load the map again to use it")

    def _check_writable(self, action: str) -> None:
        self._check_open()
        if self._read_only:
            raise MapError(
                f"cannot {action} a map loaded with read_only=True ({self._home}): load it "
                "without read_only to change it"
            )


def _remove_new_folder(target: Path) -> None:
    """Undo a folder a failed save created: its lock file, then the folder if it is empty."""
    (target / LOCK_NAME).unlink(missing_ok=True)
    try:
        target.rmdir()
    except OSError:
        pass  # not empty: something else wrote there; leave it
