"""Writing one generation of a map directory (the save protocol) and opening a saved map.

Save protocol, crash-safe at every point: write the files of generation g under temporary names,
fsync, rename, fsync the directory, then `os.replace` the manifest (the commit); older generations
are deleted only after the commit. Until then the previous manifest and every file it names are
untouched: the dense file may have grown, but only past the count the old manifest records.
`_SAVE_HOOK` is called after each step of `SAVE_STEPS` so tests can kill a save midway.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from pair_vpr_ros.errors import ConfigError, MapError, MapFingerprintError
from pair_vpr_ros.place_map.dense_store import DenseStore, read_crcs
from pair_vpr_ros.place_map.files import fsync_path, publish, same_device, write_bytes_durably
from pair_vpr_ros.place_map.index import DescriptorIndex, IndexConfig
from pair_vpr_ros.place_map.manifest import (
    Manifest,
    check_files,
    describe,
    next_generation,
    read_manifest,
    remove_generation,
    write_manifest,
)
from pair_vpr_ros.place_map.metadata import MetadataStore

SAVE_STEPS = ("dense", "dense_crc", "index", "meta", "manifest", "committed", "cleaned")
_SAVE_HOOK: Callable[[str], None] | None = None  # tests: called with each SAVE_STEPS name


def reached(step: str) -> None:
    if _SAVE_HOOK is not None:
        _SAVE_HOOK(step)


@dataclass
class MapParts:
    """The live stores of a map, as `write_generation` saves and `open_saved` returns them."""

    index: DescriptorIndex  # or a MilvusIndex (kind "milvus")
    meta: MetadataStore
    dense: DenseStore
    desc_dim: int
    dense_shape: tuple[int, int]
    fingerprint: str
    format_version: int = 2  # of the save it was opened from (1: upgraded at load)
    note: str = ""  # what the loader should log (a version-1 map's keyframes named at load)


def save(d: Path, parts: MapParts, dense_in_place: bool) -> tuple[Manifest, Path | None]:
    """Write a new generation of `d` and commit it -> (its manifest, new dense copy or None).

    On failure (disk full, ...) the files of the new generation are deleted again, except the
    live dense file when it was moved into `d`, and the previous save stays as it was.
    """
    gen = next_generation(d)
    try:
        manifest, copied = write_generation(d, gen, parts, dense_in_place)
        commit(d, manifest)
    except BaseException:
        live = parts.dense.path
        remove_generation(d, gen, keep={live.name} if live.parent == d else set())
        raise
    return manifest, copied


def write_generation(
    d: Path, gen: int, parts: MapParts, dense_in_place: bool
) -> tuple[Manifest, Path | None]:
    """Write every file of generation `gen` of `d` -> (its manifest, new dense copy or None).

    Nothing is committed: the caller makes the save visible with `commit`.

    dense_in_place: the dense file is already the one `d`'s manifest names (appends since the
    last save went there), so it is only fsynced.
    """
    dense_name, copied = _place_dense(d, gen, parts.dense, dense_in_place)
    reached("dense")
    suffix = "milvus" if parts.index.config.kind == "milvus" else "faiss"
    names = {"dense_crc": f"dense-{gen}.crc", "index": f"index-{gen}.{suffix}"}
    crcs = parts.dense.crc_bytes()
    publish(d, names["dense_crc"], lambda p: write_bytes_durably(p, crcs))
    reached("dense_crc")
    publish(d, names["index"], parts.index.write)
    reached("index")
    names["meta"] = f"meta-{gen}.sqlite"
    publish(d, names["meta"], parts.meta.save_to)
    reached("meta")
    fsync_path(d)  # the renames above are durable before a manifest names them
    files = {role: describe(d, role, name) for role, name in names.items()}
    files["dense"] = {"name": dense_name}
    manifest = Manifest(
        generation=gen,
        count=len(parts.index),
        desc_dim=parts.desc_dim,
        dense_shape=list(parts.dense_shape),
        index=asdict(parts.index.config),
        fingerprint=parts.fingerprint,
        files=files,
    )
    reached("manifest")
    return manifest, copied


def commit(d: Path, manifest: Manifest) -> None:
    """Atomically replace `d`'s manifest: from here on a load sees the new generation."""
    write_manifest(d, manifest)


def _place_dense(d: Path, gen: int, store: DenseStore, in_place: bool) -> tuple[str, Path | None]:
    """Put the valid dense entries into `d` -> (file name, path of a new copy or None)."""
    store.sync()
    if in_place:
        return store.path.name, None
    target = d / f"dense-{gen}.f16"
    if store.owned and same_device(store.path.parent, d):
        os.replace(store.path, target)  # no saved map names this file: move it, don't copy
        store.path = target
        return target.name, None
    publish(d, target.name, store.copy_to)  # a saved map names it: leave it intact
    return target.name, target


def open_saved(
    d: Path,
    expected_fingerprint: str | None,
    work: Path,
    *,
    read_only: bool,
    ef_search: int | None,
    cache_size: int,
    verify_reads: bool,
    legacy: tuple[str, str] = ("", ""),
) -> MapParts:
    """Check and open the saved map in `d`; metadata is copied to `work` (a working file).
    legacy: (robot, session) given to the keyframes of a format-version-1 map."""
    m = read_manifest(d)
    if expected_fingerprint is not None and m.fingerprint != expected_fingerprint:
        raise MapFingerprintError(
            f"place map {d} was built with model fingerprint {m.fingerprint!r}, but the current "
            f"model's fingerprint is {expected_fingerprint!r}: load it with the same weights and "
            "image size it was built with, or rebuild the map with this model (new directory)"
        )
    check_files(d, m)
    index_path = d / m.files["index"]["name"]
    config = _index_config(m, ef_search)
    if (config.kind == "milvus") != index_path.name.endswith(".milvus"):
        raise MapError(f"{index_path} is not the index file of a {config.kind!r} map: rebuild it")
    if config.kind != "milvus":
        index = _check_count(DescriptorIndex.read(index_path, m.desc_dim, config), m, index_path)
    crcs = read_crcs(d / m.files["dense_crc"]["name"], m.count)
    old = legacy if m.format_version == 1 else None
    meta = MetadataStore.from_saved(d / m.files["meta"]["name"], work, m.count, old)
    dense = None
    try:
        dense = DenseStore(
            d / m.files["dense"]["name"],
            (m.dense_shape[0], m.dense_shape[1]),
            crcs,
            writable=not read_only,
            cache_size=cache_size,
            verify_reads=verify_reads,
        )
        if config.kind == "milvus":  # last: the local files are checked before any row changes
            from pair_vpr_ros.place_map.milvus import MilvusIndex  # pymilvus only when used

            index = MilvusIndex.read(
                index_path, m.desc_dim, config, m.fingerprint, m.count, read_only
            )
    except BaseException:
        meta.close()
        if dense is not None:
            dense.close()
        raise
    shape = (m.dense_shape[0], m.dense_shape[1])
    note = "" if old is None else (
        f"place map {d} was saved before keyframes carried a robot and a session (format "
        f"version 1): its {m.count} keyframes are named robot {old[0]!r}, session {old[1]!r} "
        "(the next save stores these names)"
    )  # fmt: skip
    return MapParts(index, meta, dense, m.desc_dim, shape, m.fingerprint, m.format_version, note)


def _check_count(index: DescriptorIndex, m: Manifest, path: Path) -> DescriptorIndex:
    if len(index) != m.count:
        raise MapError(
            f"FAISS index {path} holds {len(index)} vectors, the manifest lists "
            f"{m.count}: the map is damaged, restore it from a backup or rebuild it"
        )
    return index


def _index_config(m: Manifest, ef_search: int | None) -> IndexConfig:
    try:
        config = IndexConfig(**m.index)
        return config if ef_search is None else replace(config, ef_search=int(ef_search))
    except (TypeError, ConfigError) as err:
        raise MapError(f"manifest index settings {m.index} are invalid ({err}): rebuild") from err
