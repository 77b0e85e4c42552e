"""The "milvus" place-map index: global descriptors searched in a Milvus collection.

Milvus holds what is searched (descriptor, robot, session, stamp); the dense tokens and features
stay in the map folder, keyed by keyframe id. Each map writes its rows under a random writer key
(`pk = writer << 32 | id`), so several maps (robots, runs) share one collection without
clashing, and a map only ever sees its own rows (a primary-key range in every filter).

The map keeps its own copy of the descriptors and row fields (2 KB per keyframe next to ~0.8 MB
of dense tokens) and saves them in `index-<g>.milvus` with the writer key, instead of an index
file. That copy is what makes faults harmless: while the server cannot be reached, `add` keeps
the keyframes (inserted, in id order, once it answers again) and `search` raises
`MapUnavailableError` (the pipeline counts the query as skipped); a load re-inserts rows the
collection lost and removes rows past the saved count (they have no dense tokens).
Rows that a failed call may have stored are written again with `upsert` (never duplicated).
"""

from __future__ import annotations

import logging
import secrets
from pathlib import Path

import numpy as np

from pair_vpr_ros.errors import MapError, MapUnavailableError
from pair_vpr_ros.place_map.milvus import client as mc
from pair_vpr_ros.place_map.milvus.collection import index_params, open_collection, search_params
from pair_vpr_ros.place_map.milvus.expr import (
    ID_BITS,
    MAX_WRITER,
    Exclusion,
    IdentityRuns,
    exclusion_expr,
    id_range,
    ids_expr,
)
from pair_vpr_ros.place_map.milvus.fresh import FreshRows, local_mask, local_search, merge
from pair_vpr_ros.place_map.milvus.record import read_record, write_record

CHUNK = 2000  # rows per upsert call
MAX_LIMIT = 16384  # Milvus's largest top-k
Row = tuple[str, str, float]  # robot, session, stamp of one keyframe
_log = logging.getLogger(__name__)


def _faults() -> tuple[type[BaseException], ...]:
    """Exceptions that mean "Milvus did not answer" (not a bug of ours)."""
    return (mc.pymilvus().MilvusException, ConnectionError, TimeoutError, OSError)


class MilvusIndex:
    """A DescriptorIndex-like index of `dim`-d descriptors in `config.milvus_collection`."""

    def __init__(self, dim: int, config, fingerprint: str, writer: int | None = None) -> None:
        self.dim, self.config, self.fingerprint = int(dim), config, str(fingerprint)
        self.last_training = None  # no training step (FAISS "ivf" only)
        self.uri, self.collection = config.milvus_uri, config.milvus_collection
        self.client = mc.connect(self.uri, config.milvus_token_env)
        index = index_params(config)
        self.index_type = open_collection(
            self.client, self.uri, self.collection, self.dim, self.fingerprint, index
        )
        if self.index_type != index["index_type"]:
            _log.warning(
                "place map: %s was made with a %s index, milvus_index says %s: searching it as "
                "%s (the type is fixed when a collection is made)", self._where(),
                self.index_type, index["index_type"], self.index_type,
            )  # fmt: skip
        self._desc = np.zeros((1024, self.dim), np.float32)
        self._rows: list[Row] = []
        self._runs = IdentityRuns()  # where each robot-session lies among them
        self._synced = 0  # rows [0, _synced) are in the collection
        self._unsure = 0  # rows below this may be in it already (a failed call): upsert them
        self.down = False  # the last call to Milvus failed
        self.why = "cannot be reached"  # why it failed, as messages say it
        self.local = False  # a read-only map whose rows the collection lost: searched here
        self.skipped = 0  # searches refused while Milvus was unreachable
        self._fresh = FreshRows()  # rows a Bounded search may not see yet: searched here too
        self.writer = self._new_writer() if writer is None else int(writer)
        # no saved record names this writer key (yet): its rows are deleted on close
        self.unrecorded = writer is None

    @property
    def base(self) -> int:
        return self.writer << ID_BITS

    def _where(self) -> str:
        return f"collection {self.collection!r} in {mc.where(self.uri)}"

    def _count(self, expr: str) -> int:
        found = self.client.query(self.collection, filter=expr, output_fields=["count(*)"])
        return int(found[0]["count(*)"])

    def _new_writer(self) -> int:
        """A writer key no row of the collection uses yet."""
        for _ in range(8):
            writer = secrets.randbelow(MAX_WRITER) + 1
            if not self._count(id_range(writer << ID_BITS, 0, 2**ID_BITS)):
                return writer
        raise MapError(f"no free writer key found in {self._where()} after 8 tries")

    # ------------------------------------------------------------------------- mapping

    def __len__(self) -> int:
        return len(self._rows)

    @property
    def pending(self) -> int:
        """Keyframes kept while Milvus was unreachable, not yet in the collection."""
        return len(self._rows) - self._synced

    def diagnostics(self) -> dict[str, int]:
        return {"map_searches_skipped": self.skipped, "map_keyframes_pending": self.pending}

    def add(self, desc: np.ndarray, rows: list[Row] | None = None) -> None:
        """desc [B, dim] float32 (validated, normalised); rows: (robot, session, stamp) each.
        Kept here first, then inserted; an unreachable server only delays the insert."""
        desc = np.asarray(desc, np.float32).reshape(-1, self.dim)
        if rows is None or len(rows) != len(desc):
            raise MapError("a milvus index needs robot, session and stamp for every descriptor")
        n = len(self._rows)
        if n + len(desc) >= 2**ID_BITS:
            raise MapError(f"a milvus place map holds at most {2**ID_BITS - 1} keyframes")
        while n + len(desc) > len(self._desc):
            self._desc = np.concatenate([self._desc, np.zeros_like(self._desc)])
        self._desc[n : n + len(desc)] = desc
        self._rows.extend((str(r), str(s), float(t)) for r, s, t in rows)
        self.flush()

    def flush(self) -> bool:
        """Insert the kept keyframes -> True when none is left over."""
        try:
            with mc.quiet():
                while self._synced < len(self._rows):
                    lo, hi = self._synced, min(self._synced + CHUNK, len(self._rows))
                    # insert, unless a failed call may have stored some of them: then upsert,
                    # which replaces rows of the same key instead of adding duplicates
                    write = self.client.upsert if lo < self._unsure else self.client.insert
                    write(self.collection, self._row_dicts(lo, hi))
                    self._synced = hi
                    self._fresh.written(lo)
        except _faults() as err:
            self._unsure = len(self._rows)
            full = mc.full_disk(err, self.uri)  # a lite file's disk: no server to wait for
            self.why = f"cannot store rows: {full}" if full else "cannot be reached"
            if not self.down:
                _log.warning(
                    "place map: %s %s (%s); keeping %d keyframe(s) until it answers, searches "
                    "are skipped", self._where(), self.why, mc._reason(err), self.pending,
                )  # fmt: skip
            self.down = True
            return False
        if self.down:
            _log.warning("place map: %s answers again; kept keyframes inserted", self._where())
        self.down = False
        return True

    def _row_dicts(self, lo: int, hi: int) -> list[dict]:
        return [
            {"pk": self.base + i, "robot": r, "session": s, "stamp": t, "desc": self._desc[i]}
            for i, (r, s, t) in zip(range(lo, hi), self._rows[lo:hi], strict=True)
        ]

    def reset(self) -> None:
        """Forget every keyframe: this map continues under a new writer key, so rows left
        behind are never seen again; they are deleted (if Milvus answers) unless a saved record
        names them (that folder keeps its rows)."""
        try:
            if self.unrecorded:
                self.client.delete(self.collection, filter=id_range(self.base, 0, 2**ID_BITS))
            self.writer = self._new_writer()
        except _faults() as err:
            _log.warning("place map clear: %s did not answer (%s)", self._where(), err)
            self.writer = secrets.randbelow(MAX_WRITER) + 1
        self._rows, self._synced, self._unsure = [], 0, 0
        self._fresh.clear()
        self.unrecorded = True

    def rekey(self) -> None:
        """Continue under a new writer key, the rows written again from the map's own copy:
        for a save into a new folder, so that the folder it came from keeps the old key's rows
        to itself (two folders continued apart must never write the same rows)."""
        old = self.writer
        try:
            self.writer = self._new_writer()
        except _faults() as err:
            raise MapError(f"cannot read {self._where()} ({mc._reason(err)})") from err
        self._synced = self._unsure = 0
        self._fresh.clear()
        self.unrecorded = True
        if self.flush():
            _log.info("place map: rows of writer %d copied to writer %d", old, self.writer)

    def drop(self) -> None:
        """Delete this map's rows from the collection (a map no saved folder will name: a
        failed merge); if Milvus does not answer they stay, for `pairvpr-map prune-milvus`."""
        try:
            self.client.delete(self.collection, filter=id_range(self.base, 0, 2**ID_BITS))
        except _faults() as err:
            _log.warning(
                "place map: %s did not answer (%s): the rows of writer %d stay; remove them "
                "later with pairvpr-map prune-milvus", self._where(), mc._reason(err), self.writer,
            )  # fmt: skip

    # ------------------------------------------------------------------------- queries

    def search(
        self,
        desc: np.ndarray,
        k: int,
        max_id: int | None = None,
        allowed: np.ndarray | None = None,
        exclude: tuple[int, int] | None = None,
        exclusion: Exclusion | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """desc [dim] -> (ids [k'], similarities [k']) best first, among ids <= max_id that
        `allowed` (bool [m]) lets through (or, alone, all but `exclude` = (lo, hi)), or that
        `exclusion` allows: a Milvus filter in every case.
        MapUnavailableError when Milvus cannot be reached (the caller skips the query)."""
        n = len(self._rows)
        limit = n if max_id is None else max(0, min(n, int(max_id) + 1))
        if exclude is not None and max_id is None and allowed is None:
            allowed = np.ones(n, bool)
            allowed[max(0, int(exclude[0])) : max(0, int(exclude[1]))] = False
        own = self._runs.of(self._rows, exclusion.robot, exclusion.session) if exclusion else None
        expr = exclusion_expr(self.base, limit, exclusion, own) if exclusion else None
        expr = expr if exclusion else ids_expr(self.base, limit, allowed)
        if expr is None or k <= 0:
            return np.empty(0, np.int64), np.empty(0, np.float32)
        query = np.asarray(desc, np.float32).reshape(1, self.dim)
        if self.local:  # exact, on the map's own copy: the collection lacks some of its rows
            mask = local_mask(self._rows, 0, limit, allowed, exclusion)
            return local_search(self._desc, query, 0, mask, min(int(k), MAX_LIMIT))
        if not self.flush():
            self.skipped += 1
            raise MapUnavailableError(
                f"{self._where()} {self.why}: query skipped, {self.pending} keyframe(s) kept "
                "for insertion"
            )
        level = self.config.milvus_consistency
        try:
            with mc.quiet():
                found = self.client.search(
                    self.collection, query, filter=expr, limit=min(int(k), MAX_LIMIT),
                    anns_field="desc", consistency_level=level,
                    search_params=search_params(self.config, k, self.index_type),
                )[0]  # fmt: skip
        except _faults() as err:
            self.down, self.skipped = True, self.skipped + 1
            raise MapUnavailableError(
                f"{self._where()} did not answer a search ({mc._reason(err)}): query skipped"
            ) from err
        # a server keys hits "id", milvus-lite by the primary field's name: Hit.id is either
        ids = np.array([int(hit.id) - self.base for hit in found], np.int64)
        sims = np.array([hit["distance"] for hit in found], np.float32)
        if level != "Bounded":  # Strong and Session wait until the map's own rows are visible
            return ids, sims
        lo = self._fresh.first(n)
        mask = local_mask(self._rows, lo, limit, allowed, exclusion)
        near = local_search(self._desc, query, lo, mask, min(int(k), MAX_LIMIT))
        return merge((ids, sims), near, min(int(k), MAX_LIMIT))

    def reconstruct(self, ids: np.ndarray) -> np.ndarray:
        """ids [K] (validated) -> descriptors [K, dim] float32, from the map's own copy."""
        return self._desc[np.asarray(ids, np.int64)].copy()

    def close(self) -> None:
        """Let go of the client; the rows of a map no saved record names (never saved: an
        interrupted replay, a cancelled build) are deleted first, since nothing could load them."""
        if self.unrecorded and self._rows:
            self.drop()
        try:
            self.client.close()
        except _faults():
            pass  # a server that went away has nothing to close

    # ------------------------------------------------------------------------ save / load

    def write(self, path: Path) -> None:
        """The record of this index: where its rows live, its writer key and its copy."""
        self.unrecorded = False  # from here on a save may name this key (kept even if it fails)
        write_record(path, self, self._desc[: len(self._rows)], self._rows)

    @classmethod
    def read(cls, path: Path, dim: int, config, fingerprint: str, count: int, read_only: bool):
        """Re-attach the collection recorded in `path` (checked: model, dimension) and its rows:
        missing ones are inserted again, ones past `count` (no dense tokens) are named, and
        removed unless `read_only` (a live writer of this map may be adding them)."""
        record, arrays = read_record(path, dim, count)
        mc.check_lite_exists(config.milvus_uri, Path(path).parent, read_only)
        obj = cls(dim, config, fingerprint, writer=record["writer"])
        obj._desc = np.concatenate([arrays["desc"], np.zeros((1024, obj.dim), np.float32)])
        obj._rows = list(zip(arrays["robots"].tolist(), arrays["sessions"].tolist(),
                             arrays["stamps"].tolist(), strict=True))  # fmt: skip
        obj._check_rows(count, read_only)
        return obj

    def _check_rows(self, count: int, read_only: bool) -> None:
        try:
            extra = self.client.query(
                self.collection, filter=id_range(self.base, count, 2**ID_BITS),
                output_fields=["pk"], limit=MAX_LIMIT,
            )  # fmt: skip
            held = self._count(id_range(self.base, 0, count))
        except _faults() as err:
            raise MapError(f"cannot read {self._where()} ({mc._reason(err)})") from err
        if extra:
            ids = sorted(int(r["pk"]) - self.base for r in extra)
            what = f"{len(ids)}{'+' if len(ids) == MAX_LIMIT else ''} keyframe(s) ({ids[:10]})"
            _log.warning(
                "place map: %s holds %s of this map past its saved %d keyframes, without dense "
                "tokens in the map folder (added after the last save)%s", self._where(), what,
                count, "" if read_only else ": removed",
            )  # fmt: skip
            if not read_only:
                self.client.delete(self.collection, filter=id_range(self.base, count, 2**ID_BITS))
        self._synced = count if held == count or read_only else 0
        self._unsure, self.local = count, held != count and read_only
        if held != count:  # a read-only open writes nothing: it searches its own copy
            _log.warning(
                "place map: %s held %d of this map's %d keyframes; %s", self._where(), held,
                count, "searching the map's own copy of them (a read-only open inserts "
                "nothing; a writable one inserts them again)" if read_only else
                "inserting them again",
            )  # fmt: skip
            self.flush()
