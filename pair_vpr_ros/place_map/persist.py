"""Saving a map directory (format 3) and opening a saved one (any format).

A save is incremental when the map continues the generation saved in that folder: the dense
entries appended since are fsynced, a non-flat index writes a new snapshot, and one SQLite commit
of the keyframe store (store.py) makes the new rows durable: that commit is the save's commit
point, and it writes only the new rows; then the manifest is written again as the record of the
completed save (its keyframe count and the store's identity, manifest.py), which a load checks
the store against. Otherwise (first save into a folder, save-as, a save after `clear`, an
old-format map) it writes a new generation: dense file moved or copied, the store copied,
fsynced, then `os.replace` of the manifest (its record) is the commit point. Until a commit
point the previous save is untouched: the dense file may have grown, but only past the rows its
store holds. `_SAVE_HOOK` is called after each step of `SAVE_STEPS` so tests can kill a save
midway.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from pair_vpr_ros.errors import MapError, MapFingerprintError, os_reason
from pair_vpr_ros.place_map.dense_store import DenseStore
from pair_vpr_ros.place_map.files import (
    cache_path,
    crc32_file,
    fsync_path,
    open_cache,
    publish,
    remove_quietly,
    same_device,
)
from pair_vpr_ros.place_map.index import DescriptorIndex, IndexConfig
from pair_vpr_ros.place_map.legacy import open_legacy
from pair_vpr_ros.place_map.manifest import (
    FORMAT_VERSION,
    Manifest,
    check_files,
    check_record,
    next_generation,
    read_manifest,
    remove_generation,
    write_manifest,
)
from pair_vpr_ros.place_map.parts import MapParts, SavedCrcs, check_count, index_config
from pair_vpr_ros.place_map.schema import STORE_ID
from pair_vpr_ros.place_map.store import KeyframeStore, new_id

SAVE_STEPS = ("dense", "index", "store", "manifest", "committed", "recorded", "cleaned")
_SAVE_HOOK: Callable[[str], None] | None = None  # tests: called with each SAVE_STEPS name
INDEX_FILE = "index_file"  # the store's state key naming a non-flat index snapshot
INDEX_CRC = "index_crc"  # ... and the one holding its CRC32


def reached(step: str) -> None:
    if _SAVE_HOOK is not None:
        _SAVE_HOOK(step)


def _snapshot(d: Path, gen: int, parts: MapParts) -> dict[str, str]:
    """Write the index of a non-flat kind as a new snapshot file -> the store's state rows that
    name it and its CRC32 (flat: none, the store's descriptors are the index)."""
    if parts.index.config.kind == "flat":
        return {}
    suffix = "milvus" if parts.index.config.kind == "milvus" else "faiss"
    taken = {n for n in os.listdir(d) if n.startswith(f"index-{gen}-")}
    k = next(k for k in range(len(taken) + 2) if f"index-{gen}-{k}.{suffix}" not in taken)
    path = publish(d, f"index-{gen}-{k}.{suffix}", parts.index.write)
    return {INDEX_FILE: path.name, INDEX_CRC: str(crc32_file(path))}


def save_increment(d: Path, parts: MapParts, manifest: Manifest) -> Manifest:
    """Commit the rows added since the last save of `d` (whose store `parts.store` is and whose
    manifest `manifest` is), then write its record -> the manifest now."""
    parts.dense.sync()  # the entries the new rows name are on disk before the rows
    reached("dense")
    state = _snapshot(d, parts.generation, parts)
    # written by every save, so its page is in each save's WAL frames: a -wal of another map
    # names that map (a store of format 3 gets its identity here)
    state[STORE_ID] = parts.store.store_id or new_id()
    try:
        for key, value in state.items():
            parts.store.set_state(key, value)
        reached("index")
        reached("store")
        reached("manifest")
        parts.store.commit()
    except BaseException:
        if INDEX_FILE in state:
            remove_quietly(d / state[INDEX_FILE])
        raise
    reached("committed")
    record = replace(manifest, format_version=FORMAT_VERSION, count=len(parts.index),
                     store_id=state[STORE_ID])  # fmt: skip
    try:
        write_manifest(d, record)
        fsync_path(d)
    except OSError as err:
        raise MapError(
            f"the place map was saved to {d}, but the record of this save in manifest.json "
            f"could not be written ({os_reason(err)}): free disk space and save again (the "
            "keyframes are saved)"
        ) from err
    reached("recorded")
    return record


def save(d: Path, parts: MapParts, dense_in_place: bool) -> tuple[Manifest, Path | None]:
    """Write a new generation of `d` and commit it -> (its manifest, new dense copy or None).

    On failure (disk full, ...) the files of the new generation are deleted again, except the
    live dense file when it was moved into `d`, and the previous save stays as it was.
    """
    gen = next_generation(d)
    try:
        manifest, copied = write_generation(d, gen, parts, dense_in_place)
        write_manifest(d, manifest)  # the commit point
    except BaseException:
        live = parts.dense.path
        remove_generation(d, gen, keep={live.name} if live.parent == d else set())
        raise
    return manifest, copied


def write_generation(
    d: Path, gen: int, parts: MapParts, dense_in_place: bool
) -> tuple[Manifest, Path | None]:
    """Write every file of generation `gen` of `d` -> (its manifest, new dense copy or None)."""
    dense_name, copied = _place_dense(d, gen, parts.dense, dense_in_place)
    reached("dense")
    state = _snapshot(d, gen, parts)
    reached("index")
    store_name, state[STORE_ID] = f"map-{gen}.sqlite", new_id()
    crcs = None if copied is None else parts.dense.copied_crcs  # re-coded p4 entries' rows
    publish(d, store_name, lambda p: parts.store.copy_to(p, state, crcs))
    reached("store")
    fsync_path(d)  # the renames above are durable before a manifest names them
    manifest = Manifest(
        generation=gen,
        count=len(parts.index),  # the record of this save (format 4)
        desc_dim=parts.desc_dim,
        dense_shape=list(parts.dense_shape),
        index=asdict(parts.index.config),
        fingerprint=parts.fingerprint,
        files={"store": {"name": store_name}, "dense": {"name": dense_name}},
        dense_codec=parts.dense.codec,
        store_id=state[STORE_ID],
    )
    reached("manifest")
    return manifest, copied


def _place_dense(d: Path, gen: int, store: DenseStore, in_place: bool) -> tuple[str, Path | None]:
    """Put the valid dense entries into `d` -> (file name, path of a new copy or None)."""
    store.sync()
    if in_place:
        return store.path.name, None
    target = d / f"dense-{gen}.{store.codec}"
    if store.owned and same_device(store.path.parent, d):
        os.replace(store.path, target)  # no saved map names this file: move it, don't copy
        store.path = target
        return target.name, None
    publish(d, target.name, store.copy_to)  # a saved map names it: leave it intact
    return target.name, target


def open_saved(d: Path, expected_fingerprint: str | None, work: Path, **options) -> MapParts:
    """Check and open the saved map in `d` (options: read_only, ef_search, cache_size,
    verify_reads, legacy, missing_ok); formats 1 and 2 are opened by legacy.py (a working copy
    in `work`)."""
    m = read_manifest(d)
    if expected_fingerprint is not None and m.fingerprint != expected_fingerprint:
        raise MapFingerprintError(
            f"place map {d} was built with model fingerprint {m.fingerprint!r}, but the current "
            f"model's fingerprint is {expected_fingerprint!r}: load it with the same weights and "
            "image size it was built with, or rebuild the map with this model (new directory)"
        )
    if m.format_version < 3:
        options.pop("missing_ok", None)
        return open_legacy(d, m, work, **options)
    return _open_v3(d, m, **options)


def _open_v3(
    d: Path, m: Manifest, *, read_only: bool, ef_search: int | None, cache_size: int,
    verify_reads: bool, legacy: tuple[str, str] = ("", ""), missing_ok: bool = False,
) -> MapParts:  # fmt: skip
    for entry in m.files.values():
        if not (d / entry["name"]).is_file():
            raise MapError(
                f"map file {d / entry['name']} listed in {d / 'manifest.json'} is missing: the "
                "map directory is incomplete; restore it from a backup or rebuild it"
            )
    config = index_config(m, ef_search)
    path = d / m.files["store"]["name"]
    store = KeyframeStore(path, saved=True, read_only=True)  # checked before it is written
    dense = None
    try:
        count, note = check_record(d, m, store, functools.partial(_base_id, path), missing_ok)
        index, cache = _open_index(d, store, config, m, count, read_only)
        if not read_only:
            store.close()
            store = KeyframeStore(path, saved=True)
        shape = (m.dense_shape[0], m.dense_shape[1])
        dense = DenseStore(
            d / m.files["dense"]["name"], shape, SavedCrcs(store.dense_crc, count),
            writable=not read_only, cache_size=cache_size, verify_reads=verify_reads,
            codec=m.dense_codec,
        )  # fmt: skip
    except BaseException:
        store.close()
        if dense is not None:
            dense.close()
        raise
    return MapParts(index, store, dense, m.desc_dim, shape, m.fingerprint, m.format_version,
                    note, m.generation, cache, m)  # fmt: skip


def _base_id(path: Path) -> str | None:
    """The identity the store file `path` holds without its -wal (None: it cannot be read)."""
    try:
        store = KeyframeStore(path, saved=True, wal=False)
    except MapError:
        return None
    try:
        return store.store_id
    except MapError:
        return None
    finally:
        store.close()


def _open_index(
    d: Path, store: KeyframeStore, config: IndexConfig, m: Manifest, count: int, read_only: bool
) -> tuple[object, tuple[int, int] | None]:
    """-> (the index, (count, CRC32) of the descriptor cache it was read from, or None). Kind
    "flat": the cache when it holds exactly the store's keyframes, else the store's rows."""
    if config.kind != "flat":
        return _open_snapshot(d, store, config, m, count, read_only), None
    index = DescriptorIndex(m.desc_dim, config)
    cached = open_cache(cache_path(store.path), m.desc_dim, count) if count else None
    if cached is not None:
        view, backing, crc = cached
        rows = functools.partial(_scan, store.path, m.desc_dim)
        return DescriptorIndex.viewing(m.desc_dim, config, view, backing, rows), (count, crc)
    index.add(store.scan(m.desc_dim))
    return index, None


def _scan(path: Path, desc_dim: int) -> np.ndarray:
    """The descriptors [n, desc_dim] of the last commit of the store `path`, each checked (when
    a descriptor cache fails its check)."""
    store = KeyframeStore(path, saved=True, read_only=True)
    try:
        return store.scan(desc_dim)
    finally:
        store.close()


def _open_snapshot(
    d: Path, store: KeyframeStore, config: IndexConfig, m: Manifest, count: int, read_only: bool
):
    name = store.state(INDEX_FILE)
    if name is None or "/" in name or not (d / name).is_file():
        raise MapError(
            f"the index snapshot {name!r} that {d}'s keyframe store names is missing: the map "
            "directory is incomplete; restore it from a backup or rebuild it"
        )
    if (config.kind == "milvus") != name.endswith(".milvus"):
        raise MapError(f"{d / name} is not the index file of a {config.kind!r} map: rebuild it")
    _check_snapshot(d / name, store)
    if config.kind == "milvus":
        from pair_vpr_ros.place_map.milvus.index import MilvusIndex  # pymilvus only when used

        return MilvusIndex.read(d / name, m.desc_dim, config, m.fingerprint, count, read_only)
    return check_count(DescriptorIndex.read(d / name, m.desc_dim, config), count, d / name)


def _check_snapshot(path: Path, store: KeyframeStore) -> None:
    if str(crc32_file(path)) != store.state(INDEX_CRC):
        raise MapError(
            f"index snapshot {path} fails its CRC32 check (a changed or damaged byte): the "
            "map is damaged; restore it from a backup or rebuild it"
        )


def saved_index_file(d: Path, m: Manifest) -> tuple[Path, int]:
    """(the index file, keyframes) of the saved map in `d` (a non-flat kind), files checked."""
    if m.format_version < 3:
        check_files(d, m)
        return d / m.files["index"]["name"], m.count
    store = KeyframeStore(d / m.files["store"]["name"], saved=True, read_only=True)
    try:
        path = d / (store.state(INDEX_FILE) or "?")
        if not path.is_file():
            raise MapError(f"index snapshot {path} is missing: the map directory is incomplete")
        _check_snapshot(path, store)
        return path, store.count()
    finally:
        store.close()
