"""PlaceMap: the keyframe map (global descriptors, dense tokens, metadata) with atomic save/load.

Keyframe ids are 0, 1, 2, ... in insertion order and survive save/load, so a loaded map continues
mapping where it stopped (multi-session). A loaded (or saved) map works on the saved files
themselves: its keyframe store (store.py) holds the rows added since the last save in an open
SQLite transaction, and its append-only dense file grows past the entries the saved rows name.
So a saved map changes only when `save` commits (see persist.py), and a save writes only what was
added since the last one. A never-saved map keeps its store and dense file in a working folder.
`save` and `load` are in saving.py (`MapSaving`, which PlaceMap inherits).
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

from pair_vpr_ros.errors import ConfigError, MapError, os_reason
from pair_vpr_ros.place_map.dense_codec import entry_bytes
from pair_vpr_ros.place_map.dense_store import DenseStore
from pair_vpr_ros.place_map.files import DirLock
from pair_vpr_ros.place_map.growth.tables import GrowthTables
from pair_vpr_ros.place_map.index import IndexConfig, make_index
from pair_vpr_ros.place_map.metadata import (
    KeyframeMeta,
    dense_tokens,
    keyframe_ids,
    unit_descriptor,
    validate_meta,
)
from pair_vpr_ros.place_map.milvus.expr import Exclusion, identity, utc_session
from pair_vpr_ros.place_map.saving import MapSaving
from pair_vpr_ros.place_map.store import KeyframeStore


class PlaceMap(MapSaving):
    """Keyframe map: FAISS index of [desc_dim] descriptors, [N, D] float16 dense tokens, metadata.

    desc_dim: global descriptor size (512). dense_shape: (N, D) tokens per keyframe.
    fingerprint: opaque model identity (checkpoint hash + input size + desc dim), stored on save.
    index: "flat" (exact) | "ivf" (exact below 25,000 keyframes, then k-means lists: ~1e6
        keyframes; training pauses an add, see place_map/ivf.py) | "hnsw" | an IndexConfig
        (kind "milvus": a Milvus collection, see place_map/milvus/index.py and docs/milvus.md);
        its `dense_codec` ("p4" default, "q4", "q4a", "f16") is how dense tokens are stored.
    dense_cache_size: dense entries kept in memory (LRU). verify_dense_reads: CRC32-check
    entries read from disk. work_dir: parent of the working folder of a never-saved map (default:
    $TMPDIR); put it on the disk of the map directory so the first save moves the dense file.
    dense_weight: codec p4: the pair decoder's first layer W [C, D] (`set_dense_weight`).
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
        dense_weight: np.ndarray | None = None,
    ) -> None:
        config = index if isinstance(index, IndexConfig) else IndexConfig(kind=index)
        if int(desc_dim) < 1 or len(dense_shape) != 2 or min(dense_shape) < 1:
            raise ConfigError(f"bad place map shape: desc_dim={desc_dim}, dense={dense_shape}")
        self._setup(dense_cache_size, verify_dense_reads, work_dir)
        self._dense_weight = dense_weight
        self.desc_dim = int(desc_dim)
        self.dense_shape = (int(dense_shape[0]), int(dense_shape[1]))
        self.fingerprint = str(fingerprint)
        self._codec = config.dense_codec
        self._store = self._fresh_store()
        self._dense = self._fresh_dense()
        try:
            self._index = make_index(self.desc_dim, config, self.fingerprint)
        except BaseException:
            self.close()
            raise

    def _setup(self, cache_size: int, verify_reads: bool, work_dir) -> None:
        self._cache_size, self._verify_reads = int(cache_size), bool(verify_reads)
        self._index: Any = None  # DescriptorIndex (FAISS) or MilvusIndex
        self._store: KeyframeStore | None = None
        self._dense: DenseStore | None = None
        self._home: Path | None = None  # directory of the last load/save (we hold its lock)
        self._lock: DirLock | None = None
        self._dense_committed = False  # the dense file is the one `_home`'s manifest names
        self._generation = 0  # of `_home` (its store is `_store` when `_store.saved`)
        self._desc_cache: tuple[int, int] | None = None  # (count, CRC32) of its cache file
        self._manifest = None  # of `_home` (format 3+): the record each save writes again
        self._read_only = False
        self.load_note = ""  # what a caller should log about the load ("" = nothing)
        self._fresh_count = 0
        self._dense_weight: np.ndarray | None = None
        self._closed = False
        self.session = utc_session()  # of keyframes that name none (see `identity`)
        try:
            self._tmp = Path(tempfile.mkdtemp(prefix="pairvpr-map-", dir=work_dir))
        except OSError as err:
            where = work_dir or tempfile.gettempdir()  # $TMPDIR: a full one said as such
            raise MapError(f"cannot create a working folder in {where}: {os_reason(err)}") from err
        self._remove_tmp = weakref.finalize(self, shutil.rmtree, self._tmp, True)

    def _fresh_dense(self) -> DenseStore:
        self._fresh_count += 1
        path = self._tmp / f"dense-work-{self._fresh_count}.{self._codec}"
        reads = dict(cache_size=self._cache_size, verify_reads=self._verify_reads)
        return DenseStore(path, self.dense_shape, owned=True, codec=self._codec,
                          weight=self._dense_weight, **reads)  # fmt: skip

    def _fresh_store(self) -> KeyframeStore:
        self._fresh_count += 1
        return KeyframeStore(self._tmp / f"store-work-{self._fresh_count}.sqlite", saved=False)

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
            crc = self._dense.crcs[kf_id]
            self._store.add(replace(meta, id=kf_id), query, crc, bytes(features))
            self._index.add(query[None], [(*self.identity(meta), meta.stamp)])
        except BaseException as err:
            undo = ""
            try:
                self._store.delete_from(kf_id)
            except sqlite3.Error as again:  # a full disk fails the clean-up too: say both
                undo = f"; undoing it failed too ({again})"
            self._dense.drop_last()
            if isinstance(err, sqlite3.Error) or undo:
                if undo:  # the store may hold part of it
                    undo += ": its rows may be half written; save nothing more and load the "
                    raise MapError(f"storing keyframe {kf_id} failed: {os_reason(err)}{undo}"
                                   "map's last save") from err  # fmt: skip
                raise MapError(
                    f"storing keyframe {kf_id} failed: {os_reason(err)}; the map keeps its "
                    f"{kf_id} keyframes: free disk space and go on"
                ) from err
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

    def search_peers(self, desc: np.ndarray, k: int, robot: str, peers: tuple[str, ...] = ()):
        """desc [desc_dim] -> up to k keyframes of robots other than `robot` (of `peers`, when
        given) in this map's shared Milvus collection, best first: [milvus.peers.PeerRow]
        (fleet_peer_search "milvus"). MapError for another index kind; MapUnavailableError
        when the server does not answer."""
        self._check_open()
        if not self.filters_in_index:
            raise MapError(
                f"searching other robots' keyframes needs a place map of index kind 'milvus', "
                f"this one is {self._index.config.kind!r}: set index to milvus (a shared "
                "collection) or fleet_peer_search to broadcast"
            )
        from pair_vpr_ros.place_map.milvus.peers import search_peers  # pymilvus when used

        return search_peers(self._index, unit_descriptor(desc, self.desc_dim), k, robot, peers)

    def get_dense(self, ids: Iterable[int]) -> np.ndarray:
        """ids [K] -> dense tokens [K, N, D] float16."""
        return self._dense.read(keyframe_ids(ids, len(self)))

    def get_desc(self, ids: Iterable[int]) -> np.ndarray:
        """ids [K] -> stored (L2-normalised) descriptors [K, desc_dim] float32."""
        return self._index.reconstruct(keyframe_ids(ids, len(self)))

    def meta(self, kf_id: int) -> KeyframeMeta:
        """Metadata of one keyframe; MapError if the id is not in the map."""
        self._check_open()
        found = self._store.get(kf_id)
        if found is None and 0 <= kf_id < len(self):  # a row gone from a saved store
            raise self._store.damaged(f"has no row for keyframe {kf_id} (rows are missing)")
        if found is None:
            raise MapError(f"keyframe {kf_id} is not in the map (ids 0..{len(self) - 1})")
        return found

    def features(self, kf_id: int) -> bytes:
        """Packed features of a keyframe (b"": none, e.g. a map saved before features were
        kept); MapError for an unknown id or damaged bytes."""
        self.meta(kf_id)
        return self._store.features(kf_id)

    def feature_stats(self) -> tuple[int, int]:
        """(keyframes with features, bytes of all their features)."""
        self._check_open()
        return self._store.feature_stats()

    @property
    def growth(self) -> GrowthTables:
        """Appearance signatures, links and represented keyframes (growth/tables.py), in the
        store's open transaction: a save commits them with the keyframes."""
        self._check_open()
        return self._store.growth(writable=not self._read_only)

    def all_meta(self) -> list[KeyframeMeta]:
        """Every keyframe's metadata, by id (for plots and markers)."""
        self._check_open()
        return self._store.all()

    def __len__(self) -> int:
        self._check_open()
        return len(self._index)

    def clear(self) -> None:
        """Forget every keyframe (ids restart at 0); the last save stays as it is until `save`."""
        self._check_writable("clear")
        self._index.reset()
        old_store, self._store = self._store, self._fresh_store()
        old_store.close()  # a saved store: its unsaved rows are rolled back, its save kept
        old, self._dense = self._dense, self._fresh_dense()
        self._discard(old)
        self._dense_committed = False

    def drop_index_rows(self) -> None:
        """Kind "milvus": delete this map's rows from the collection. Only for a map that no
        saved folder names (a failed merge): a saved map would lose its rows until its next
        load. Other kinds: nothing to do."""
        self._check_open()
        if self.filters_in_index:
            self._index.drop()

    def set_dense_weight(self, weight: np.ndarray | None) -> None:
        """Codec p4: fit the basis (when it is fitted: at keyframe BASIS_FROM) for the pair
        decoder's first layer W [C, D] (dense_codec.py); a fitted basis is kept."""
        self._dense_weight = self._dense.weight = weight

    @property
    def dense_basis(self):
        """Codec p4: the fitted `dense_codec.Basis`, else None."""
        return self._dense.basis

    def adopt_dense_basis(self, basis) -> None:
        """Code this empty p4 map's tokens with `basis` from its first keyframe (a merge or
        compact keeps its input's basis); nothing for other codecs or shapes, or no basis."""
        if basis is not None and self._codec == "p4" and len(self) == 0:
            if len(basis.mean) == self.dense_shape[1]:
                self._dense.adopt(basis)

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
        return entry_bytes(self.dense_shape, self._codec) + 4 * self.desc_dim

    @property
    def directory(self) -> Path | None:
        """The map directory last loaded from or saved to (None for a never-saved map)."""
        return self._home

    # ------------------------------------------------------------------------ life cycle

    def close(self) -> None:
        """Release files, the directory lock and the working folder (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self._dense is not None:
            self._discard(self._dense)
        if self._store is not None:
            self._store.close()
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
