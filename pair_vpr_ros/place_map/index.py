"""FAISS inner-product index over L2-normalised global descriptors; ids are insertion positions.

Recent keyframes are excluded with an `IDSelectorRange` (an id prefix), an `IDSelectorNot` of one
(all ids but one range: another session's recent keyframes) or an `IDSelectorBitmap` (any set of
ids) passed as search parameters, so FAISS only ever ranks eligible ids: k results
come back even when thousands of newer frames are closer.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from pathlib import Path

import faiss
import numpy as np

from pair_vpr_ros.errors import ConfigError, MapError
from pair_vpr_ros.place_map.dense_codec import DEFAULT_CODEC, check_codec
from pair_vpr_ros.place_map.ivf import IvfIndex, Training, check_loaded, omp_threads, read_bounded
from pair_vpr_ros.place_map.milvus.collection import check_milvus_settings

INDEX_KINDS = ("flat", "hnsw", "ivf", "milvus")
# Smallest value of each integer IndexConfig field (39: FAISS's k-means minimum for one list).
LOWEST = dict(hnsw_m=1, ef_construction=1, ef_search=1, nlist=0, nprobe=1, train_at=39,
              exact_below=0, search_threads=0)  # fmt: skip


@dataclass(frozen=True)
class IndexConfig:
    """How descriptors are searched.

    kind: "flat" = exact inner product (`IndexFlatIP`); "hnsw" = approximate graph search
        (`IndexHNSWFlat`, inner product); "ivf" = exact until `train_at` keyframes, then an
        inverted file of k-means lists trained on the map (`IndexIVFFlat`, see ivf.py): the
        kind for maps of ~1e5-1e6 keyframes (docs/performance.md "Place map").
    hnsw_m: HNSW neighbours per node (M); memory ~ 2*M*4 bytes per keyframe on top of the vector.
    ef_construction: HNSW candidate list while inserting; higher = better graph, slower add.
    ef_search: HNSW candidate list while searching (raised to k when k is larger); recall vs time.
    nlist: "ivf" lists; 0 = 4 sqrt(n) at each training (n = keyframes then, at most n/39).
    nprobe: "ivf" lists scanned per search; recall vs time (32: recall@10 1.000, 2.5 ms at 1e6
        trajectory-shaped keyframes, docs/performance.md "Place map").
    train_at: "ivf" is exact (flat) below this many keyframes and trained on the add that
        reaches it (or 39 x nlist with a fixed nlist, if more).
    retrain_growth: "ivf" trains again each time the map grows this factor past the last
        training (> 1; 0 = never again).
    exact_below: with "hnsw" or "ivf", a search with at most this many eligible ids scans them
        exactly instead (cheap at that size, and a filtered graph search can miss a few).
    search_threads: OpenMP threads for one search and one "ivf" add (0 = FAISS default). 1 by
        default: a single query is latency-bound, and on a 2-core machine FAISS's fan-out made
        a flat search of 1e5 keyframes 4x slower (63 ms vs 17 ms, see benchmarks/bench_map.py).
    milvus_uri: kind "milvus": a milvus-lite file (path ending in .db, created if missing; a
        relative path is made absolute) or a server / cluster address (http(s)://host:port).
    milvus_collection: the Milvus collection (several maps may share one: docs/milvus.md).
    milvus_index: the collection's vector index: IVF_FLAT (default: recall@10 1.000 at 1e5,
        docs/milvus.md), HNSW or FLAT (exact); nlist (0: 1024) / nprobe, hnsw_m /
        ef_construction / ef_search apply to it.
    milvus_token_env: environment variable holding the Milvus token ("" or unset: none); the
        token itself is never stored, logged or taken as a parameter.
    dense_codec: how the map stores dense tokens (not a search setting, but carried here so the
        map's settings travel as one): "p4" (a basis per map, 200 KiB per ViT-B keyframe),
        "q4" (4-bit per channel, same size, faster to decode), "q4a" (4-bit on each channel's
        range, same size) or "f16" (uncompressed, 794 KiB); dense_codec.py. A loaded map keeps
        its own.
    milvus_consistency: how a search sees the map's own latest inserts: "Bounded" (default: no
        wait for the server's time tick; the rows written in the last 10 s are searched in
        the node too), "Session" or "Strong" (the server waits for the tick, ~200 ms).
    """

    kind: str = "flat"
    hnsw_m: int = 32
    ef_construction: int = 80
    ef_search: int = 64
    nlist: int = 0
    nprobe: int = 32
    train_at: int = 25_000
    retrain_growth: float = 4.0
    exact_below: int = 4096
    search_threads: int = 1
    milvus_uri: str = ""
    milvus_collection: str = "pairvpr_keyframes"
    milvus_index: str = "IVF_FLAT"
    milvus_token_env: str = "PAIRVPR_MILVUS_TOKEN"
    dense_codec: str = DEFAULT_CODEC
    milvus_consistency: str = "Bounded"

    def __post_init__(self) -> None:
        check_codec(self.dense_codec)
        if self.kind not in INDEX_KINDS:
            raise ConfigError(f"place map index must be one of {INDEX_KINDS}, got {self.kind!r}")
        for name, low in LOWEST.items():
            value = getattr(self, name)
            if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < low:
                raise ConfigError(f"IndexConfig.{name} must be an integer >= {low}, got {value!r}")
        growth = self.retrain_growth
        if (
            isinstance(growth, bool)
            or not isinstance(growth, numbers.Real)
            or not (growth == 0 or 1 < growth < math.inf)
        ):
            raise ConfigError(
                f"IndexConfig.retrain_growth must be a number > 1 (retrain when the map has "
                f"grown that factor) or 0 (never retrain), got {growth!r}"
            )
        if self.kind == "milvus":
            object.__setattr__(self, "milvus_uri", check_milvus_settings(self))


class DescriptorIndex:
    """Wraps a FAISS index of `dim`-d float32 vectors; id i = the i-th vector added."""

    cache_failed = False  # a viewed descriptor cache failed its check (`viewing`)

    def __init__(self, dim: int, config: IndexConfig | None = None) -> None:
        if config is not None and config.kind == "milvus":
            raise ConfigError("index kind 'milvus' is a MilvusIndex: use make_index")
        self.dim = int(dim)
        self.config = config or IndexConfig()
        self._set(self._new_index())

    def _new_index(self) -> faiss.Index:
        if self.config.kind in ("flat", "ivf"):  # ivf starts exact: IvfIndex trains it later
            return faiss.IndexFlatIP(self.dim)
        index = faiss.IndexHNSWFlat(self.dim, self.config.hnsw_m, faiss.METRIC_INNER_PRODUCT)
        index.hnsw.efConstruction = self.config.ef_construction
        index.hnsw.efSearch = self.config.ef_search
        return index

    @property
    def config(self) -> IndexConfig:
        return self._config

    @config.setter
    def config(self, config: IndexConfig) -> None:
        """Search settings may change on a live index (benchmarks sweep nprobe / efSearch)."""
        self._config = config
        if getattr(self, "_ivf", None) is not None:
            self._ivf.config = config

    @classmethod
    def viewing(
        cls, dim: int, config: IndexConfig, index: faiss.Index, backing: tuple, fallback
    ) -> DescriptorIndex:
        """A "flat" index over vectors it does not own (a loaded map's descriptor cache,
        files.open_cache: `backing` = (map, rows, CRC32 check)): its first use makes
        the check (rows that fail it are replaced by `fallback()` [n, dim], and `cache_failed`
        says so), its first change copies them."""
        obj = cls(dim, config)
        obj._set(index)
        obj._backing, obj._fallback = backing, fallback
        return obj

    def _checked(self) -> None:
        if self._backing is None or self._backing[2] is None:
            return
        mm, view, check = self._backing
        self._backing = (mm, view, None)
        if not check.ok():
            self._set(self._new_index())
            self._index.add(self._fallback())
            self.cache_failed = True

    def _own(self) -> None:
        """FAISS cannot grow or cut a view: copy the viewed vectors into an index of its own."""
        self._checked()
        if self._backing is None:
            return
        view = self._backing[1]  # uint8 [faiss header + rows]: the rows after the header
        rows = view[view.size - 4 * self.dim * len(self) :].view(np.float32)
        own = self._new_index()
        own.add(rows.reshape(-1, self.dim))
        self._set(own)

    def _set(self, index: faiss.Index) -> None:
        self._backing = None
        self._ivf = IvfIndex(self.dim, self.config, index) if self.config.kind == "ivf" else None
        self._faiss = index

    @property
    def _index(self) -> faiss.Index:
        """The FAISS index now (an "ivf" index replaces its own when it trains)."""
        return self._faiss if self._ivf is None else self._ivf.index

    @property
    def last_training(self) -> Training | None:
        """The last "ivf" training in this process (None: none, or another kind)."""
        return None if self._ivf is None else self._ivf.last_training

    def __len__(self) -> int:
        return int(self._index.ntotal)

    def add(self, desc: np.ndarray, rows: list | None = None) -> None:
        """desc [B, dim] float32 (already validated and normalised). With "ivf", the add that
        reaches a training size trains the index first (a pause: see ivf.py). `rows` (robot,
        session, stamp per descriptor) are for the "milvus" kind; FAISS kinds ignore them."""
        desc = np.ascontiguousarray(desc, dtype=np.float32).reshape(-1, self.dim)
        self._own()
        (self._index if self._ivf is None else self._ivf).add(desc)

    def reset(self) -> None:
        self._set(self._new_index())

    def truncate(self, count: int) -> None:
        """Kind "flat": forget ids >= count (a save that lost its unsaved keyframes)."""
        self._own()
        self._index.remove_ids(faiss.IDSelectorRange(int(count), len(self)))

    def search(
        self,
        desc: np.ndarray,
        k: int,
        max_id: int | None = None,
        allowed: np.ndarray | None = None,
        exclude: tuple[int, int] | None = None,
        exclusion: object | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """desc [dim] -> (ids [k'] int64, similarities [k'] float32), best first, ids <= max_id
        and, with `allowed` (bool [m]), only ids i < m with allowed[i]; with `exclude` (lo, hi)
        (and neither of the others) no id in lo..hi-1. `exclusion` (the rules as an index
        filter) is for kind "milvus": FAISS kinds take the others.

        k' = min(k, number of eligible ids); never returns FAISS's -1 padding.
        """
        if exclusion is not None:
            raise MapError("search(exclusion=...) needs index kind 'milvus'; pass allowed=")
        self._checked()
        limit = len(self) if max_id is None else min(len(self), int(max_id) + 1)
        if exclude is not None and max_id is None and allowed is None:
            count, selector = _not_range(len(self), *exclude)
        else:
            count, selector = self._selector(limit, allowed)
        k = min(int(k), count)
        if k <= 0:
            return np.empty(0, np.int64), np.empty(0, np.float32)
        query = np.ascontiguousarray(desc, dtype=np.float32).reshape(1, self.dim)
        with omp_threads(self.config.search_threads):
            ids, sims = self._search(query, k, count, selector)
        keep = ids[0] >= 0
        return ids[0][keep].astype(np.int64), sims[0][keep].astype(np.float32)

    def _selector(
        self, limit: int, allowed: np.ndarray | None
    ) -> tuple[int, faiss.IDSelector | None]:
        """(how many ids are eligible, FAISS selector or None for all): ids < `limit` that
        `allowed` lets through."""
        if allowed is not None:
            allowed = np.asarray(allowed, dtype=bool)[: max(limit, 0)]
            ids = np.flatnonzero(allowed)
            if len(ids) < len(allowed) and len(ids):  # not a prefix: a bitmap of the ids
                bits = np.packbits(allowed, bitorder="little")
                selector = faiss.IDSelectorBitmap(len(bits), faiss.swig_ptr(bits))  # n: bytes
                selector.referenced_objects = [bits]  # FAISS keeps a pointer, not the array
                return len(ids), selector
            limit = len(ids)
        selector = faiss.IDSelectorRange(0, limit) if limit < len(self) else None
        return limit, selector

    def _search(
        self, query: np.ndarray, k: int, count: int, selector: faiss.IDSelector | None
    ) -> tuple[np.ndarray, np.ndarray]:
        if self._ivf is not None and self._ivf.trained:
            sims, ids = self._ivf.search(query, k, count, selector)
        elif self.config.kind != "hnsw":  # flat, and ivf before its first training
            sims, ids = self._flat_search(self._index, query, k, selector)
        elif count <= self.config.exact_below:
            sims, ids = self._flat_search(self._storage(), query, k, selector)
        else:
            params = faiss.SearchParametersHNSW(efSearch=max(self.config.ef_search, k))
            if selector is not None:
                params.sel = selector
            sims, ids = self._index.search(query, k, params=params)
            if int((ids[0] >= 0).sum()) < k:
                # The filtered graph walk found fewer than k eligible nodes (rare: only when
                # the selector excludes most of the map); an exact scan is then correct.
                sims, ids = self._flat_search(self._storage(), query, k, selector)
        return ids, sims

    @staticmethod
    def _flat_search(
        index: faiss.Index, query: np.ndarray, k: int, selector: faiss.IDSelector | None
    ) -> tuple[np.ndarray, np.ndarray]:
        if selector is None:
            return index.search(query, k)
        return index.search(query, k, params=faiss.SearchParameters(sel=selector))

    def _storage(self) -> faiss.Index:
        return faiss.downcast_index(self._index.storage)

    def reconstruct(self, ids: np.ndarray) -> np.ndarray:
        """ids [K] (validated) -> descriptors [K, dim] float32."""
        if len(ids) == 0:
            return np.empty((0, self.dim), np.float32)
        self._checked()
        return self._index.reconstruct_batch(np.asarray(ids, dtype=np.int64))

    def write(self, path: Path) -> None:
        faiss.write_index(self._index, str(path))

    @classmethod
    def read(cls, path: Path, dim: int, config: IndexConfig) -> DescriptorIndex:
        """Load a file written by `write`; the stored kind must be `config.kind`."""
        index = read_bounded(path)
        want = {"flat": faiss.IndexFlatIP, "hnsw": faiss.IndexHNSWFlat}.get(config.kind)
        want = want or (faiss.IndexFlatIP, faiss.IndexIVFFlat)  # ivf: before / after training
        if not isinstance(index, want) or index.d != dim:
            raise MapError(
                f"FAISS index {path} is a {type(index).__name__} of dim {index.d}, but the "
                f"manifest says {config.kind!r} of dim {dim}: the map is damaged, rebuild it"
            )
        if index.metric_type != faiss.METRIC_INNER_PRODUCT:
            raise MapError(f"FAISS index {path} does not use inner product: rebuild the map")
        if isinstance(index, faiss.IndexIVFFlat):
            index = check_loaded(index, path)
        obj = cls.__new__(cls)
        obj.dim, obj.config = int(dim), config
        obj._set(index)
        if config.kind == "hnsw":
            index.hnsw.efConstruction = config.ef_construction
            index.hnsw.efSearch = config.ef_search
        return obj


def _not_range(size: int, lo: int, hi: int) -> tuple[int, faiss.IDSelector | None]:
    """(eligible count, selector) of every id in 0..size-1 except lo..hi-1."""
    lo, hi = max(0, int(lo)), min(size, int(hi))
    if hi <= lo:
        return size, None
    inner = faiss.IDSelectorRange(lo, hi)
    selector = faiss.IDSelectorNot(inner)
    selector.referenced_objects = [inner]  # FAISS keeps a pointer, not the object
    return size - (hi - lo), selector


def make_index(dim: int, config: IndexConfig, fingerprint: str):
    """A new empty index of `config.kind`: DescriptorIndex (FAISS) or MilvusIndex."""
    if config.kind == "milvus":
        from pair_vpr_ros.place_map.milvus.index import MilvusIndex  # pymilvus only when used

        return MilvusIndex(dim, config, fingerprint)
    return DescriptorIndex(dim, config)
