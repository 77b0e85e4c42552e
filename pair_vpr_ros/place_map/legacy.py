"""Opening maps of formats 1 and 2 (before issue 34): index, metadata SQLite, CRC file and float16
dense file, checked as they always were, then converted to a working format-3 store.

The working store (in the map's working folder) takes every keyframe's metadata, descriptor,
dense CRC32 and features; the float16 dense file is used where it is, and the next save into the
folder writes format 3 around it (`dense_codec` f16: its tokens are not re-encoded).
"""

from __future__ import annotations

from array import array
from pathlib import Path

import numpy as np

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map.dense_store import DenseStore
from pair_vpr_ros.place_map.index import DescriptorIndex
from pair_vpr_ros.place_map.manifest import FORMAT_VERSION, Manifest, check_files
from pair_vpr_ros.place_map.metadata import MetadataStore, identity_problem
from pair_vpr_ros.place_map.parts import MapParts, check_count, index_config
from pair_vpr_ros.place_map.store import KeyframeStore

_CHUNK = 1024


def open_legacy(
    d: Path, m: Manifest, work: Path, *, read_only: bool, ef_search: int | None,
    cache_size: int, verify_reads: bool, legacy: tuple[str, str] = ("", ""),
) -> MapParts:  # fmt: skip
    """Check and open the format-1/2 map in `d`; its store is built in the folder `work`.
    legacy: (robot, session) given to the keyframes of a format-version-1 map."""
    check_files(d, m)
    index_path = d / m.files["index"]["name"]
    config = index_config(m, ef_search)
    if (config.kind == "milvus") != index_path.name.endswith(".milvus"):
        raise MapError(f"{index_path} is not the index file of a {config.kind!r} map: rebuild it")
    if config.kind != "milvus":
        index = check_count(
            DescriptorIndex.read(index_path, m.desc_dim, config), m.count, index_path
        )
    crcs = read_crcs(d / m.files["dense_crc"]["name"], m.count)
    old = legacy if m.format_version == 1 else None
    meta = MetadataStore.from_saved(
        d / m.files["meta"]["name"], work / "meta-old.sqlite", m.count, old
    )
    store, dense = KeyframeStore(work / "store.sqlite", saved=False), None
    try:
        shape = (m.dense_shape[0], m.dense_shape[1])
        dense = DenseStore(
            d / m.files["dense"]["name"], shape, crcs, writable=not read_only,
            cache_size=cache_size, verify_reads=verify_reads, codec="f16",
        )  # fmt: skip
        if config.kind == "milvus":  # last: the local files are checked before any row changes
            from pair_vpr_ros.place_map.milvus.index import MilvusIndex  # pymilvus only when used

            index = MilvusIndex.read(
                index_path, m.desc_dim, config, m.fingerprint, m.count, read_only
            )
        _convert(meta, store, index, crcs, d / m.files["meta"]["name"])
    except BaseException:
        store.close()
        if dense is not None:
            dense.close()
        raise
    finally:
        meta.close()
        (work / "meta-old.sqlite").unlink(missing_ok=True)
    named = "" if old is None else (
        f"; its {m.count} keyframes are named robot {old[0]!r}, session {old[1]!r}"
    )  # fmt: skip
    note = (
        f"place map {d} is of format version {m.format_version}{named}: loaded through a working "
        f"copy, converted to format {FORMAT_VERSION} by the next save into it (dense tokens stay "
        "float16)"
    )
    return MapParts(index, store, dense, m.desc_dim, shape, m.fingerprint, m.format_version, note)


def _convert(meta: MetadataStore, store: KeyframeStore, index, crcs, saved: Path) -> None:
    """Every keyframe of the old metadata into the new store, with its descriptor and CRC; a
    robot or session name that breaks the identity rule (written before it) is refused."""
    rows = meta.all()
    for robot, session in sorted({(r.robot, r.session) for r in rows}):
        problem = identity_problem(robot, session)
        if problem:
            raise MapError(
                f"keyframe metadata {saved}: its keyframes' {problem}; "
                "the map was written before robot and session names were checked: rebuild it "
                "with valid names"
            )
    for lo in range(0, len(rows), _CHUNK):
        chunk = rows[lo : lo + _CHUNK]
        descs = index.reconstruct(np.array([r.id for r in chunk], np.int64))
        for row, desc in zip(chunk, descs, strict=True):
            store.add(row, desc, crcs[row.id], meta.features(row.id))


def read_crcs(path: Path, count: int) -> array:
    """Read a format-1/2 `dense-g.crc` file (little-endian uint32 each) -> `count` CRC32s."""
    data = path.read_bytes()
    if len(data) != 4 * count:
        raise MapError(
            f"dense checksum file {path} holds {len(data) // 4} entries, the manifest lists "
            f"{count}: the map is damaged, restore it from a backup or rebuild it"
        )
    crcs = array("I")
    crcs.frombytes(np.frombuffer(data, dtype="<u4").astype(np.uint32).tobytes())
    return crcs
