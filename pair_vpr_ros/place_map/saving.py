"""Save and load of a `PlaceMap` (`MapSaving`, the class it inherits them from): atomic, crash-safe
saves (the steps are in persist.py) and loads that check everything before they trust it.

`MapSaving` works on the PlaceMap's own state (its index, metadata, dense store, directory lock);
it is not used on its own.
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path
from typing import TypeVar

import numpy as np

from pair_vpr_ros.errors import MapError, MapFingerprintError
from pair_vpr_ros.identity import DEFAULT_ROBOT, LEGACY_SESSION
from pair_vpr_ros.place_map import persist
from pair_vpr_ros.place_map.dense_store import DenseStore
from pair_vpr_ros.place_map.files import (
    CACHE_SUFFIX,
    LOCK_NAME,
    DirLock,
    cache_path,
    fsync_path,
    write_cache,
)
from pair_vpr_ros.place_map.manifest import MANIFEST_NAME, Manifest, read_manifest, remove_stale
from pair_vpr_ros.place_map.parts import MapParts, SavedCrcs
from pair_vpr_ros.place_map.store import KeyframeStore

# The class `load` is called on (PlaceMap): saving.py never imports place_map.py, which imports it.
MapT = TypeVar("MapT", bound="MapSaving")


class MapSaving:
    """`save` and `load` of PlaceMap (place_map.py holds the state they work on)."""

    def flush(self) -> None:
        """The slow half of the next save, safe to run on another thread while keyframes are
        added (they append past it): fsync the dense tokens added so far. The save then fsyncs
        only what came after, and commits."""
        dense = self._dense
        try:
            if dense is not None and not self._closed:
                dense.sync()
        except (OSError, TypeError):  # closed or replaced meanwhile: the save syncs its own
            pass

    def checkpoint(self) -> None:
        """Fold the saved rows from the keyframe store's WAL into its file (any thread)."""
        store = self._store
        if store is not None and not self._closed:
            store.checkpoint()

    def save(
        self, directory: str | os.PathLike, overwrite: bool = False, checkpoint: bool = True
    ) -> Path:
        """Atomically make `directory` hold this map (created if needed) -> its resolved path.

        A crash at any moment leaves the previous save in `directory` loadable and intact. After
        a save the map continues in that directory: later saves there write only the keyframes
        added since (persist.py).
        A map of another model saved there is refused (MapFingerprintError) unless `overwrite`.
        A failed save into a folder it created leaves no folder behind. Kind "milvus": a save
        into another folder than the last one writes the rows again under a new writer key
        (the last folder keeps its own rows; cost: one insert of every keyframe).
        checkpoint=False: leave the WAL for a `checkpoint` call on another thread (MapControl).
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
        # p4 entries re-coded with the basis (dense_store.py) need a copy: a new generation
        in_place = self._dense_committed and target == self._home
        in_place = in_place and not self._dense.recode_pending
        if self._home is not None and target != self._home and self.filters_in_index:
            self._index.rekey()  # milvus: `_home` keeps its rows, this save gets its own
        increment = in_place and self._store.saved
        try:
            if increment:
                self._manifest = persist.save_increment(target, self._parts(), self._manifest)
            else:
                manifest, copied = persist.save(target, self._parts(), in_place)
        except BaseException as err:
            if increment and self._store.rolled_back:
                self._store.rolled_back = False
                self._lost_unsaved(err)  # SQLite rolled the unsaved rows back itself
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
        if increment:
            self._after_increment(target)
        else:
            self._after_commit(target, manifest, copied, new_lock)
        self._update_desc_cache()
        if checkpoint:
            self._store.checkpoint()
        return target

    def _lost_unsaved(self, err: BaseException) -> None:
        """A failed commit (disk full) that SQLite answered with a rollback dropped the rows
        added since the last save: go back to the last save, so the live map stays consistent."""
        saved, count = self._store.count(), len(self._index)
        if self._index.config.kind != "flat":
            self.close()
            raise MapError(
                f"saving the place map to {self._home} failed ({err}) and dropped the "
                f"{count - saved} keyframes added since the last save; the map is closed: free "
                "disk space and load it again (the last save is intact)"
            ) from err
        self._index.truncate(saved)
        self._dense.truncate(saved)
        raise MapError(
            f"saving the place map to {self._home} failed ({err}); the {count - saved} keyframes "
            f"added since the last save are dropped, the map continues from the last save "
            f"({saved} keyframes): free disk space and save again"
        ) from err

    def _update_desc_cache(self) -> None:
        """Append the saved keyframes' descriptors to the flat descriptor cache next to the
        store (dense_store.py; derived data: if this fails, the next load scans the rows)."""
        if self._index.config.kind != "flat" or not self._store.saved:
            return
        count, crc = self._desc_cache or (0, 0)
        n = len(self._index)
        if count > n or self._index.cache_failed:  # written again, whole
            count, crc, self._index.cache_failed = 0, 0, False
        try:
            if n > count:
                rows = self._index.reconstruct(np.arange(count, n))
                self._desc_cache = (n, write_cache(cache_path(self._store.path), rows, count, crc))
        except (OSError, RuntimeError):
            self._desc_cache = None  # the next save writes it whole

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

    def _parts(self) -> MapParts:
        return MapParts(
            self._index, self._store, self._dense, self.desc_dim, self.dense_shape,
            self.fingerprint, generation=self._generation,
        )  # fmt: skip

    def _after_increment(self, d: Path) -> None:
        keep = {self._store.state(persist.INDEX_FILE)} - {None}
        remove_stale(d, self._keep(d, keep))
        persist.reached("cleaned")

    def _keep(self, d: Path, names: set) -> set[str]:
        """Files of the saved map in `d`: the manifest's, the store's WAL, the index snapshot."""
        store = self._store.path.name
        return names | {MANIFEST_NAME, LOCK_NAME, self._dense.path.name, store,
                        store + "-wal", store + "-shm", store + "-journal",
                        store + CACHE_SUFFIX}  # fmt: skip

    def _after_commit(
        self, d: Path, manifest: Manifest, copied: Path | None, lock: DirLock | None
    ) -> None:
        """Bookkeeping once `d` holds the new save; if it fails, the next save copies again."""
        self._dense_committed, self._desc_cache = False, None  # a new store: a new cache
        old_store = self._store
        if isinstance(self._dense.crcs, SavedCrcs):  # read through the store closed below
            self._dense.crcs = self._dense.crcs.materialised()
        if copied is None:
            self._dense.owned = False  # a save names this file now: never move or delete it
        if lock is not None:
            if self._lock is not None:
                self._lock.release()
            self._lock, self._home = lock, d
        self._manifest = manifest
        persist.reached("committed")
        persist.reached("recorded")  # the manifest of a new generation is its record
        try:
            if copied is not None:  # continue in the new copy; the old file stays with its save
                old = self._dense
                self._dense = DenseStore(
                    copied,
                    self.dense_shape,
                    old.crcs if old.copied_crcs is None else old.copied_crcs,
                    cache_size=self._cache_size,
                    verify_reads=self._verify_reads,
                    codec=old.codec,
                    weight=old.weight,
                )
                self._discard(old)
            fsync_path(d)  # make the manifest switch durable before deleting what it replaced
            self._store = KeyframeStore(d / manifest.files["store"]["name"], saved=True)
            old_store.close()  # its rows are in the new store now
            self._generation, self._dense_committed = manifest.generation, True
        except OSError as err:
            raise MapError(
                f"the place map was saved to {d}, but finishing the save failed ({err}); "
                "save again to make sure it is on disk"
            ) from err
        remove_stale(d, self._keep(d, {self._store.state(persist.INDEX_FILE)} - {None}))
        persist.reached("cleaned")

    @classmethod
    def load(
        cls: type[MapT],
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
        missing_ok: bool = False,
    ) -> MapT:
        """Open a saved map to continue mapping (or only to query, with read_only=True).
        legacy_identity: (robot, session) of the keyframes of a format-1 map (`load_note`).
        missing_ok: a keyframe store that holds fewer keyframes than its last completed save
        recorded (its -wal lost) loads with what it holds, `load_note` saying what is missing
        (default: MapError); a save then records what it holds.

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
                obj._tmp,
                read_only=read_only,
                ef_search=ef_search,
                cache_size=obj._cache_size,
                verify_reads=obj._verify_reads,
                legacy=legacy_identity,
                missing_ok=missing_ok,
            )
            obj._index, obj._store, obj._dense = parts.index, parts.store, parts.dense
            if verify_dense:
                obj._dense.verify_all()
        except BaseException:
            obj.close()
            raise
        obj.desc_dim, obj.dense_shape = parts.desc_dim, parts.dense_shape
        obj.fingerprint, obj._codec = parts.fingerprint, parts.dense.codec
        obj._home, obj._dense_committed, obj._read_only = d, True, read_only
        obj._generation, obj._desc_cache = parts.generation, parts.desc_cache
        obj.load_note, obj._manifest = parts.note, parts.manifest
        return obj


def _remove_new_folder(target: Path) -> None:
    """Undo a folder a failed save created: its lock file, then the folder if it is empty."""
    (target / LOCK_NAME).unlink(missing_ok=True)
    try:
        target.rmdir()
    except OSError:
        pass  # not empty: something else wrote there; leave it
