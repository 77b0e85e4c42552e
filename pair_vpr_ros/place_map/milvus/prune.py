"""Removing stale rows from a Milvus keyframe collection (`pairvpr-map prune-milvus`).

Rows are keyed `pk = writer << 32 | keyframe id` (index.py), and a saved map names its writer
key and keyframe count in its record (`index-<g>.milvus`). A row is stale when no saved map
refers to it: its writer key is named by none (a run that was never saved: an interrupted
replay, a merge that failed), or its id is at or past the largest saved count of its writer
(keyframes added after the last save, without dense tokens). Nothing ever searches such rows.

The saved maps are found under the folders the caller gives (every manifest.json below them);
a map there that cannot be read stops the prune, because its rows could not be told apart. A
map of the collection is kept whatever URI its record names (a moved file still belongs to its
maps). A saved map whose folder was not given loses its rows, but gets them back on its next
load: its record holds its own copy of them (index.py).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from pair_vpr_ros.errors import ConfigError, MapError
from pair_vpr_ros.place_map.index import IndexConfig
from pair_vpr_ros.place_map.manifest import MANIFEST_NAME, read_manifest
from pair_vpr_ros.place_map.milvus import client as mc
from pair_vpr_ros.place_map.milvus.collection import check_layout, ensure_loaded
from pair_vpr_ros.place_map.milvus.expr import ID_BITS, id_range
from pair_vpr_ros.place_map.milvus.record import read_record
from pair_vpr_ros.place_map.persist import saved_index_file

BATCH = 1000  # rows per query-iterator page


@dataclass
class StaleWriter:
    """The stale rows of one writer key."""

    writer: int
    rows: int = 0
    first_id: int = 2**ID_BITS
    last_id: int = -1
    saved_count: int | None = None  # of the saved map with this key (None: no saved map)
    names: set[str] = field(default_factory=set)  # "robot/session" of its rows

    def line(self) -> str:
        why = "no saved map" if self.saved_count is None else f"past its saved {self.saved_count}"
        return (
            f"stale: writer {self.writer}: {self.rows} rows, ids {self.first_id}..{self.last_id} "
            f"({why}), {', '.join(sorted(self.names))}"
        )


@dataclass
class PruneResult:
    where: str  # "collection 'x' in milvus-lite file ..."
    total: int  # rows before
    maps: list[str]  # saved map folders of this collection
    kept: int  # rows they refer to
    stale: list[StaleWriter]
    removed: int = 0  # 0 on a dry run

    @property
    def stale_rows(self) -> int:
        return sum(s.rows for s in self.stale)

    def lines(self) -> list[str]:
        out = [
            f"{self.where}: {self.total} rows, {self.kept} kept for {len(self.maps)} saved "
            f"map(s), {self.stale_rows} stale"
        ]
        out += [s.line() for s in self.stale]
        if self.removed:
            out.append(f"removed {self.removed} stale rows; {self.total - self.removed} remain")
        elif self.stale:
            out.append(f"dry run: {self.stale_rows} stale rows not removed; pass --yes to remove")
        return out


def prune_milvus(
    uri: str,
    map_dirs: Sequence[str | os.PathLike],
    collection: str = "pairvpr_keyframes",
    apply: bool = False,
    token_env: str = "PAIRVPR_MILVUS_TOKEN",
) -> PruneResult:
    """List (and with `apply`, delete) the rows of `collection` at `uri` that no saved map
    under `map_dirs` refers to -> PruneResult. ConfigError: bad arguments, a missing lite file;
    MapError: Milvus cannot be opened, the collection is missing or not ours, a map under
    `map_dirs` cannot be read. Nothing is deleted unless every check passed."""
    # IndexConfig checks the URI and the name (the texts of the bad-input matrix)
    config = IndexConfig(
        kind="milvus", milvus_uri=uri, milvus_collection=collection, milvus_token_env=token_env
    )
    uri, place = config.milvus_uri, f"collection {collection!r} in {mc.where(config.milvus_uri)}"
    if mc.is_lite(uri) and not Path(uri).exists():
        raise ConfigError(
            f"milvus-lite file {uri} does not exist: give the file the maps were made with "
            "(their milvus_uri)"
        )
    if mc.is_lite(uri) and Path(uri).is_dir() and not mc.is_lite_folder(Path(uri)):
        raise MapError(
            f"{uri} is not a milvus-lite file (no LOCK file and collections folder in it): give "
            "the file the maps were made with (their milvus_uri)"
        )
    saved = saved_writers(map_dirs, collection)
    client = mc.connect(uri, token_env)
    try:
        return _prune(client, uri, collection, saved, apply)
    except mc.pymilvus().MilvusException as err:
        raise MapError(f"{place} did not answer ({mc._reason(err)}): nothing removed") from err
    finally:
        client.close()


def _prune(client, uri: str, collection: str, saved: dict, apply: bool) -> PruneResult:
    place = f"collection {collection!r} in {mc.where(uri)}"
    if not client.has_collection(collection):
        raise MapError(
            f"{place} does not exist (collections there: {sorted(client.list_collections())}): "
            "give --collection the maps' milvus_collection"
        )
    check_layout(client.describe_collection(collection), place)
    ensure_loaded(client, collection)
    keep = " or ".join(id_range(w << ID_BITS, 0, n) for w, (n, _) in sorted(saved.items()))
    stale_expr = f"not ({keep})" if keep else "pk >= 0"
    total = _count(client, collection, "pk >= 0")
    stale = _stale_writers(client, uri, collection, stale_expr, saved)
    maps = sorted({d for _, dirs in saved.values() for d in dirs})
    result = PruneResult(place, total, maps, total - sum(s.rows for s in stale), stale)
    if apply and stale:
        client.delete(collection, filter=stale_expr)
        left = _count(client, collection, "pk >= 0")
        result.removed = total - left
    return result


def _count(client, collection: str, expr: str) -> int:
    found = client.query(collection, filter=expr, output_fields=["count(*)"])
    return int(found[0]["count(*)"])


def _stale_writers(client, uri: str, collection: str, expr: str, saved: dict) -> list[StaleWriter]:
    groups: dict[int, StaleWriter] = {}
    # milvus-lite has no server-side snapshot time for iterators; pymilvus warns and uses its
    # own clock, which is right here (no writer holds a lite file while we do)
    quiet = logging.getLogger("pymilvus.client.iterator.query_iterator")
    was, quiet.disabled = quiet.disabled, mc.is_lite(uri)
    try:
        pages = client.query_iterator(
            collection, batch_size=BATCH, filter=expr, output_fields=["pk", "robot", "session"]
        )
    finally:
        quiet.disabled = was
    try:
        while rows := pages.next():
            for row in rows:
                writer, kf_id = divmod(int(row["pk"]), 2**ID_BITS)
                group = groups.setdefault(
                    writer, StaleWriter(writer, saved_count=saved.get(writer, (None,))[0])
                )
                group.rows += 1
                group.first_id = min(group.first_id, kf_id)
                group.last_id = max(group.last_id, kf_id)
                group.names.add(f"{row['robot']}/{row['session']}")
    finally:
        pages.close()
    return [groups[w] for w in sorted(groups)]


def saved_writers(map_dirs: Sequence[str | os.PathLike], collection: str) -> dict:
    """{writer key: (largest saved count, [map folders])} of the saved maps under `map_dirs`
    whose index is `collection` (any URI). MapError when one of them cannot be read."""
    out: dict[int, tuple[int, list[str]]] = {}
    if not map_dirs:
        raise ConfigError("give the folders of the saved maps (--maps DIR ...)")
    for root in map_dirs:
        root = Path(root).expanduser().resolve()
        if not root.is_dir():
            raise ConfigError(f"--maps {root} does not exist or is not a folder")
        for d in _map_folders(root):
            try:
                m = read_manifest(d)
                if m.index.get("kind") != "milvus":
                    continue
                path, count = saved_index_file(d, m)
                record, _ = read_record(path, m.desc_dim, count)
            except MapError as err:
                raise MapError(
                    f"saved map {d} cannot be read ({err}); its rows cannot be told from stale "
                    "ones: repair the map or move it out of the folders given, then prune again"
                ) from err
            if record["collection"] == collection:
                saved = count
                count, dirs = out.get(int(record["writer"]), (0, []))
                out[int(record["writer"])] = (max(count, saved), [*dirs, str(d)])
    return out


def _map_folders(root: Path) -> list[Path]:
    """Folders under `root` (itself included) holding a manifest.json, in sorted order;
    milvus-lite data folders are not entered (their collections hold manifest.json files)."""
    found = []
    for here, subdirs, files in os.walk(root):
        if mc.is_lite_folder(Path(here)):
            subdirs.clear()
            continue
        subdirs.sort()
        if MANIFEST_NAME in files:
            found.append(Path(here))
    return sorted(found)
