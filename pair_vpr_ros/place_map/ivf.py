"""The "ivf" place-map index: exact search while the map is small, then an inverted file.

An IVF-Flat index (`IndexIVFFlat`, inner product) splits the map into `nlist` k-means lists and
scans only the `nprobe` lists nearest the query. Its lists must be trained on the map's own
descriptors, and the map grows one keyframe at a time, so the index goes through stages:

- below `train_at` keyframes (at least 39 per list, FAISS's k-means minimum): an exact
  `IndexFlatIP`, as the "flat" kind;
- on the add that reaches it: k-means on a sample of at most 50 descriptors per list
  (10 iterations), then every descriptor moves into the IVF index, in id order;
- each time the map grows `retrain_growth` times past the last training (train_at x 4, x 16,
  ... by default): trained again, so the lists follow the map (nlist 4 sqrt(n) grows with it).

The training runs inside `add`, so that one add pauses the caller: measured with
benchmarks/bench_map.py (docs/performance.md "Place map"); `last_training` and a logged
warning say how long.
Ids stay insertion positions: IVF adds number vectors ntotal, ntotal + 1, ... and a direct map
(id -> list slot) keeps `reconstruct` working. Every list holds its ids in increasing order
(vectors are always added in id order), which lets a range selector bisect each list.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import faiss
import numpy as np

from pair_vpr_ros.errors import MapError

TRAIN_POINTS_PER_LIST = 50  # k-means sample per list (FAISS warns below 39); bounds train time
KMEANS_ITERATIONS = 10  # FAISS's default 25 costs 2.5x the k-means time
MOVE_CHUNK = 65536  # descriptors copied at a time when (re)building: peak = old + new index
SMALL_ADD = 256  # adds of at most this many run on `search_threads` threads (see add)
_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Training:
    """One (re)training: map size, lists, k-means sample size, wall time (s) of train + move."""

    keyframes: int
    nlist: int
    sample: int
    seconds: float


class IvfIndex:
    """The FAISS index behind an "ivf" DescriptorIndex (`self.index`: IndexFlatIP, then
    IndexIVFFlat) and its training schedule. `config` is the IndexConfig (kind "ivf")."""

    def __init__(self, dim: int, config, index: faiss.Index | None = None) -> None:
        self.dim, self.config = int(dim), config
        self.index = faiss.IndexFlatIP(self.dim) if index is None else index
        self.last_training: Training | None = None
        # Stage of the last training (-1: none). A loaded IVF index was trained at the stage
        # its size is in: training happens on the add that enters a stage.
        self._stage = self.stage(self.index.ntotal) if self.trained else -1

    @property
    def trained(self) -> bool:
        return isinstance(self.index, faiss.IndexIVFFlat)

    def first_training_size(self) -> int:
        """Keyframes at which the map is first trained: train_at, or 39 x a fixed nlist."""
        return max(int(self.config.train_at), 39 * int(self.config.nlist))

    def stage(self, n: int) -> int:
        """-1 below the first training size, then s for n in [T g^s, T g^(s+1)) (g = growth;
        0 for good when retrain_growth is 0)."""
        first, growth = self.first_training_size(), float(self.config.retrain_growth)
        if n < first:
            return -1
        if growth == 0:
            return 0
        s = int(math.floor(math.log(n / first, growth)))
        while first * growth ** (s + 1) <= n:  # floating-point slack at exact powers
            s += 1
        while s > 0 and first * growth**s > n:
            s -= 1
        return s

    def nlist_for(self, n: int) -> int:
        """Lists for a map of n keyframes: the configured nlist, else 4 sqrt(n) (at most n/39)."""
        if self.config.nlist:
            return int(self.config.nlist)
        return max(1, min(round(4 * math.sqrt(n)), n // 39))

    def add(self, desc: np.ndarray) -> None:
        """desc [B, dim] float32 C-contiguous; trains when the map enters a new stage. Either
        everything happens or, on an error (even mid-training), nothing does."""
        stage = self.stage(int(self.index.ntotal) + len(desc))
        if stage > self._stage:
            self.train(desc)
            self._stage = stage
        elif len(desc) <= SMALL_ADD:
            # One keyframe: FAISS's OpenMP fan-out over the lists only waits for a second
            # thread; on a busy 2-core machine an add took 12 ms on 2 threads, 25 µs on 1.
            with omp_threads(self.config.search_threads):
                self.index.add(desc)
        else:
            self.index.add(desc)

    def train(self, extra: np.ndarray) -> Training:
        """k-means on a sample of the map and `extra` [B, dim] (the descriptors being added),
        then a new IVF index holding all of them replaces the current one."""
        t0 = time.perf_counter()
        old, n_old = self.index, int(self.index.ntotal)
        n = n_old + len(extra)
        nlist = self.nlist_for(n)
        size = min(n, TRAIN_POINTS_PER_LIST * nlist)
        picks = np.sort(np.random.default_rng(n).choice(n, size, replace=False))
        sample = np.concatenate(
            [
                old.reconstruct_batch(picks[picks < n_old].astype(np.int64)),
                extra[picks[picks >= n_old] - n_old],
            ]
        )
        new = faiss.IndexIVFFlat(
            faiss.IndexFlatIP(self.dim), self.dim, nlist, faiss.METRIC_INNER_PRODUCT
        )
        new.cp.niter = KMEANS_ITERATIONS
        new.cp.spherical = True  # unit centroids: the lists of an inner-product space
        new.train(sample)
        del sample
        new.make_direct_map()  # array id -> (list, slot): reconstruct(id)
        for lo in range(0, n_old, MOVE_CHUNK):  # in id order, so every list stays sorted by id
            new.add(old.reconstruct_n(lo, min(MOVE_CHUNK, n_old - lo)))
        new.add(extra)
        self.index = new
        self.last_training = Training(n, nlist, size, time.perf_counter() - t0)
        # A warning: the add that trained paused its caller (the node's frames) this long.
        _log.warning(
            "place map ivf index trained at %d keyframes: %d lists, k-means on %d; this add "
            "paused %.1f s", n, nlist, size, self.last_training.seconds,
        )  # fmt: skip
        return self.last_training

    def search(
        self, query: np.ndarray, k: int, count: int, selector: faiss.IDSelector | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """query [1, dim] -> (similarities [1, k], ids [1, k], -1 padded); `count` eligible ids.
        Trained indexes only (before, DescriptorIndex searches the flat index as "flat" does).

        Probes `nprobe` lists; scans all of them (exact) when count <= exact_below or when the
        probed lists held fewer than k eligible ids (a selector that excludes most of them)."""
        assert self.trained, "an untrained ivf index is searched as a flat one"
        if isinstance(selector, faiss.IDSelectorRange):
            selector.assume_sorted = True  # ids rise within each list: bisect, not test each
        nlist = int(self.index.nlist)
        exact = count <= self.config.exact_below
        sims, ids = self._probe(query, k, nlist if exact else self.config.nprobe, selector)
        if not exact and int((ids[0] >= 0).sum()) < k:
            sims, ids = self._probe(query, k, nlist, selector)
        return sims, ids

    def _probe(self, query, k: int, nprobe: int, selector) -> tuple[np.ndarray, np.ndarray]:
        params = faiss.SearchParametersIVF(nprobe=min(int(nprobe), int(self.index.nlist)))
        if selector is not None:
            params.sel = selector
        return self.index.search(query, k, params=params)


@contextmanager
def omp_threads(threads: int) -> Iterator[None]:
    """Run the block on `threads` OpenMP threads (0: unchanged); FAISS's setting is per calling
    thread (an OpenMP ICV), and is restored afterwards."""
    before = faiss.omp_get_max_threads()
    if threads:
        faiss.omp_set_num_threads(threads)
    try:
        yield
    finally:
        faiss.omp_set_num_threads(before)


def check_loaded(index: faiss.Index, path) -> faiss.Index:
    """An IndexIVFFlat read from `path`: its quantizer must be a trained IndexFlatIP with one
    centroid per list and its ids 0..ntotal-1 (a direct map is rebuilt if absent)."""
    quantizer = faiss.downcast_index(index.quantizer)
    if (
        not index.is_trained
        or not isinstance(quantizer, faiss.IndexFlatIP)
        or quantizer.ntotal != index.nlist
    ):
        raise MapError(
            f"FAISS index {path} is an untrained or inconsistent IVF index ({index.nlist} lists, "
            f"quantizer {type(quantizer).__name__} of {quantizer.ntotal}): the map is damaged, "
            "rebuild it"
        )
    if index.direct_map.type != faiss.DirectMap.Array:
        try:
            index.make_direct_map()
        except RuntimeError as err:
            raise MapError(
                f"FAISS index {path} holds ids other than 0..{index.ntotal - 1}: the map is "
                "damaged, rebuild it"
            ) from err
    return index


def read_bounded(path: Path) -> faiss.Index:
    """faiss.read_index, but no array it allocates may be larger than the file itself: a damaged
    size field then fails at once instead of asking for terabytes (MemoryError) or zero-filling
    gigabytes. The limit is process-wide in FAISS, so it is restored afterwards."""
    try:
        size = path.stat().st_size
    except OSError as err:
        raise MapError(f"FAISS index {path} cannot be read: {err.strerror}") from err
    previous = faiss.get_deserialization_vector_byte_limit()
    # FAISS compares element counts against limit / (4 * itemsize) for some arrays.
    faiss.set_deserialization_vector_byte_limit(min(previous, 4 * (size + 1)))
    try:
        return faiss.read_index(str(path))
    except (RuntimeError, MemoryError) as err:
        reason = str(err).splitlines()[-1][:200] if str(err) else type(err).__name__
        if "deserialization_vector_byte_limit" in str(err):
            reason = "an array size field exceeds the file size"
        raise MapError(
            f"FAISS index {path} could not be read ({reason}); the map is damaged: restore it "
            "from a backup or rebuild it"
        ) from err
    finally:
        faiss.set_deserialization_vector_byte_limit(previous)
