"""`manifest.json`: the one file that says which generation of map files is the saved map, and
the record of its last completed save.

Format 3 (written since issue 34): generation g is `map-g.sqlite` (the keyframe store, store.py:
metadata, descriptors, features, per-row CRC32s; its own commits are the incremental saves) and
the append-only `dense-h.q4` / `.p4` / `.q4a` / `.f16` (p4: its basis in the file's head);
non-flat index kinds add a snapshot `index-g-k.faiss` / `.milvus` that the store names. The
manifest carries a CRC32 of its own content. Format 4 (issue 48) is format 3 plus the record
of each completed save: after every save's commit the manifest is written again with `count`,
the keyframes that save holds, and `store_id`, the identity of the keyframe store it names
(its `state` row). That record lives outside the store's write-ahead log, so a load finds a
`-wal` that was deleted, truncated, replaced or left behind (fewer keyframes than recorded)
and a store or `-wal` of another map (another identity). In format 3 `count` was the
keyframes of the generation's first save, which the store always holds, so the same check
holds for it; the next save writes format 4 (the store's schema migrated, schema.py).

Formats 1 and 2 (read, converted to 3 by the next save): files of generation g are named
`index-g.faiss` (kind "milvus": `index-g.milvus`, the record of its collection), `meta-g.sqlite`,
`dense-g.crc`; the dense file keeps the name of the generation that created it (`dense-h.f16`,
h <= g) because saves appended to it; replacing the manifest was the commit point of a save.
"""

from __future__ import annotations

import json
import os
import re
import zlib
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.hashing import sha256_file
from pair_vpr_ros.place_map.dense_codec import CODECS
from pair_vpr_ros.place_map.files import TMP_SUFFIX, remove_quietly, write_bytes_durably

MANIFEST_NAME = "manifest.json"
FORMAT_NAME = "pair_vpr_ros.place_map"
# 2: keyframes carry robot and session (issue 22); 3: incremental (34); 4: the record of each
# completed save, the store's identity and schema version (48)
FORMAT_VERSION = 4
READABLE_VERSIONS = (1, 2, 3, 4)  # a version-1 map loads with its keyframes named at load
# Files a save may create; anything else in the directory is left alone.
MAP_FILE_RE = re.compile(
    r"^(index-\d+(-\d+)?\.(faiss|milvus)|(meta|map)-\d+\.sqlite|dense-\d+\.(f16|crc|q4a|q4|p4))"
)
_SINCE_4 = {"store_id": ""}  # fields added by format 4, left out of the CRC at their default
_CHECKED = ("index", "meta", "dense_crc")  # small files: size + sha256 in the manifest
_ROLE_RE_V3 = {
    "store": re.compile(r"map-\d+\.sqlite"),
    "dense": re.compile(r"dense-\d+\.(f16|q4a|q4|p4)"),
}
_ROLE_RE = {
    "index": re.compile(r"index-\d+\.(faiss|milvus)"),  # milvus: the collection's record
    "meta": re.compile(r"meta-\d+\.sqlite"),
    "dense_crc": re.compile(r"dense-\d+\.crc"),
    "dense": re.compile(r"dense-\d+\.f16"),
}


@dataclass
class Manifest:
    """Everything needed to open a saved map and to check its files."""

    generation: int
    count: int  # format 4: keyframes of the last completed save (3: of the generation's first)
    desc_dim: int
    dense_shape: list[int]
    index: dict  # IndexConfig fields
    fingerprint: str
    files: dict  # role -> {"name", "size", "sha256"}; role "dense" has only "name"
    format: str = FORMAT_NAME
    format_version: int = FORMAT_VERSION
    dense_dtype: str = "float16"
    dense_codec: str = "f16"  # how dense entries are stored (dense_codec.py); 1 and 2: f16
    checksum: int = 0  # format 3: CRC32 of the manifest's other fields
    store_id: str = ""  # format 4: the keyframe store's identity (its state row STORE_ID)

    def content_crc(self) -> int:
        data = asdict(self)
        data.pop("checksum")
        for name, default in _SINCE_4.items():  # a format-3 manifest's CRC has none of them
            if data[name] == default:
                data.pop(name)
        return zlib.crc32(json.dumps(data, sort_keys=True).encode())

    def file_names(self) -> set[str]:
        return {f["name"] for f in self.files.values()}


def describe(directory: Path, role: str, name: str) -> dict:
    """-> the manifest entry of a written file (size + sha256 for the checked roles)."""
    entry = {"name": name}
    if role in _CHECKED:
        path = directory / name
        entry.update(size=path.stat().st_size, sha256=sha256_file(path))
    return entry


def write_manifest(directory: Path, manifest: Manifest) -> None:
    """Atomically make `manifest` the saved map of `directory` (the commit point).

    The directory entry is fsynced by the caller (`fsync_path(directory)`) once it has recorded
    the commit, so that a failing fsync cannot hide that the switch happened.
    """
    tmp = directory / (MANIFEST_NAME + TMP_SUFFIX)
    manifest.checksum = manifest.content_crc()
    data = asdict(manifest)
    data = {"format": data.pop("format"), "format_version": data.pop("format_version"), **data}
    try:
        write_bytes_durably(tmp, (json.dumps(data, indent=2) + "\n").encode())
        os.replace(tmp, directory / MANIFEST_NAME)
    except BaseException:
        remove_quietly(tmp)
        raise


def read_manifest(directory: Path) -> Manifest:
    """Parse and validate `directory/manifest.json`; MapError naming the problem otherwise."""
    path = directory / MANIFEST_NAME
    if not path.is_file():
        raise MapError(
            f"{path} is missing: {directory} is not a saved place map (or its save never "
            "completed); pass the directory given to PlaceMap.save, or build a new map"
        )
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise MapError(f"{path} is not valid JSON ({err}): the map is damaged, rebuild") from err
    if not isinstance(raw, dict) or raw.get("format") != FORMAT_NAME:
        raise MapError(f"{path} is not a pair_vpr_ros place map manifest (no format field)")
    version = raw.get("format_version")
    if version not in READABLE_VERSIONS or isinstance(version, bool):
        raise MapError(
            f"{path} has format_version {version!r}, this version of pair_vpr_ros reads "
            f"versions {', '.join(map(str, READABLE_VERSIONS))}: use a matching pair_vpr_ros "
            "release or rebuild the map"
        )
    try:
        manifest = Manifest(**raw)
        _check_fields(manifest)
    except (TypeError, ValueError, KeyError) as err:
        raise MapError(f"{path} has missing or invalid fields ({err}): rebuild the map") from err
    if version >= 3 and manifest.checksum != manifest.content_crc():
        raise MapError(
            f"{path} fails its CRC32 check (a changed or damaged byte): the map is damaged; "
            "restore it from a backup or rebuild it"
        )
    return manifest


def _check_fields(m: Manifest) -> None:
    if not (isinstance(m.generation, int) and isinstance(m.count, int) and m.count >= 0):
        raise ValueError("generation/count must be integers >= 0")
    if not (isinstance(m.desc_dim, int) and m.desc_dim > 0 and len(m.dense_shape) == 2):
        raise ValueError("desc_dim must be > 0 and dense_shape [N, D]")
    if not all(isinstance(v, int) and v > 0 for v in m.dense_shape):
        raise ValueError("dense_shape entries must be integers > 0")
    if m.dense_dtype != "float16" or not isinstance(m.fingerprint, str):
        raise ValueError("dense_dtype must be float16 and fingerprint a string")
    if not isinstance(m.store_id, str) or (m.store_id and m.format_version < 4):
        raise ValueError(f"bad store_id {m.store_id!r}")
    if m.dense_codec not in CODECS or (m.format_version < 3 and m.dense_codec != "f16"):
        raise ValueError(f"unknown dense_codec {m.dense_codec!r}")
    roles = _ROLE_RE_V3 if m.format_version >= 3 else _ROLE_RE
    if set(m.files) != set(roles):
        raise ValueError(f"files must list exactly {sorted(roles)}")
    for role, pattern in roles.items():
        name = m.files[role]["name"]
        if not isinstance(name, str) or not pattern.fullmatch(name):
            raise ValueError(f"bad file name for {role}: {name!r}")


def check_files(directory: Path, manifest: Manifest) -> None:
    """Every file is present; the small ones have the recorded size and sha256."""
    for role, entry in manifest.files.items():
        path = directory / entry["name"]
        if not path.is_file():
            raise MapError(
                f"map file {path} ({role}) listed in {directory / MANIFEST_NAME} is missing: "
                "the map directory is incomplete; restore it from a backup or rebuild it"
            )
        if role not in _CHECKED:
            continue
        size = path.stat().st_size
        if size != entry.get("size") or sha256_file(path) != entry.get("sha256"):
            raise MapError(
                f"map file {path} ({role}) does not match its checksum in "
                f"{directory / MANIFEST_NAME} (size {size}, recorded {entry.get('size')}): the "
                "file is damaged or from another save; restore it from a backup or rebuild the map"
            )


def next_generation(directory: Path) -> int:
    """1 + the highest generation named by the manifest or by any map file in `directory`."""
    gens = [0]
    try:
        gens.append(read_manifest(directory).generation)
    except MapError:
        pass  # a damaged or missing manifest is replaced by this save
    for name in os.listdir(directory):
        if MAP_FILE_RE.match(name):
            gens.append(int(re.findall(r"\d+", name)[0]))
    return max(gens) + 1


def remove_stale(directory: Path, keep: set[str]) -> None:
    """Delete map files (and temporaries) of older or failed saves that `keep` does not name."""
    for name in os.listdir(directory):
        stale = MAP_FILE_RE.match(name) or name.startswith(MANIFEST_NAME + TMP_SUFFIX)
        if stale and name not in keep:
            remove_quietly(directory / name)  # a leftover is harmless: the next save retries


def remove_generation(directory: Path, generation: int, keep: set[str]) -> None:
    """Delete the files (and temporaries) a failed save of `generation` left, except `keep`."""
    pattern = re.compile(
        rf"^(index|meta|dense|map)-{generation}(-\d+)?\.(faiss|milvus|sqlite|f16|crc|q4a|q4|p4)"
    )
    for name in os.listdir(directory):
        if pattern.match(name) and name not in keep:
            remove_quietly(directory / name)


def check_record(
    d: Path, m: Manifest, store, base_id: Callable[[], str | None], missing_ok: bool = False
) -> tuple[int, str]:
    """Check the keyframe store `store` of the map in `d` (opened through its write-ahead log)
    against `m`'s record of the last completed save -> (its keyframe count, a note: "" or, with
    `missing_ok`, what is missing). MapError: the store or its -wal belongs to another map (a
    store identity other than the record's), or it holds fewer keyframes than recorded.
    base_id(): the identity in the store's file read without its -wal (None: unreadable)."""
    wal = Path(f"{store.path}-wal")
    try:
        count = store.count_checked()
        found = store.store_id if m.store_id else ""
    except MapError as err:  # pages of another map's log over this file read as damage
        if m.store_id and wal.exists() and base_id() == m.store_id:
            raise _foreign_wal(store.path, wal, "its pages do not fit this store") from err
        raise
    if m.store_id and found != m.store_id:
        if wal.exists() and base_id() == m.store_id:
            raise _foreign_wal(store.path, wal, f"it names store {found or '?'!r}")
        raise MapError(
            f"keyframe store {store.path} belongs to another map (store {found or '?'!r}; "
            f"{d / MANIFEST_NAME} names {m.store_id!r}): it was replaced by another map's; "
            "restore the map folder from a backup, or load the map it belongs to"
        )
    if count >= m.count:
        return count, ""
    if store.wal_ignored:
        why = (f"its write-ahead log {wal.name} cannot be read here (SQLite must write "
               f"{store.path.name}-shm beside it: a read-only folder?)")  # fmt: skip
    elif wal.exists():
        why = f"its write-ahead log {wal.name} is truncated or older than that save"
    else:
        why = (f"its write-ahead log {wal.name} is missing (deleted, or the folder was copied "
               "without it while the map was open)")  # fmt: skip
    lost = f"{m.count - count} keyframes ({count}..{m.count - 1})"
    note = (
        f"keyframe store {store.path} holds {count} keyframes, the last completed save "
        f"recorded {m.count} ({d / MANIFEST_NAME}): {lost} are missing; {why}"
    )
    if missing_ok:
        return count, note
    raise MapError(
        f"{note}: copy the map folder again with its {wal.name} (close the map first, or copy "
        "the folder whole), or restore it from a backup; to go on with the "
        f"{count} keyframes it holds: pairvpr-map compact {d} --out NEW_FOLDER"
    )


def _foreign_wal(path: Path, wal: Path, how: str) -> MapError:
    return MapError(
        f"keyframe store {path}: its write-ahead log {wal.name} belongs to another map ({how}; "
        f"the store's own file is this map's): the map's own log was replaced; move {wal.name} "
        "away and load the map again (it then holds the keyframes its file holds), or restore "
        "the map folder from a backup"
    )
