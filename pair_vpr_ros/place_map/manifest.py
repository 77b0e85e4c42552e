"""`manifest.json`: the one file that says which generation of map files is the saved map.

Format 3 (written since issue 34): generation g is `map-g.sqlite` (the keyframe store, store.py:
metadata, descriptors, features, per-row CRC32s; its own commits are the incremental saves) and
the append-only `dense-h.q4` / `.p4` / `.q4a` / `.f16` (p4: its basis in the file's head);
non-flat index kinds add a snapshot `index-g-k.faiss` / `.milvus` that the store names. The
manifest is written only when a generation starts (first save into a folder, a save after
`clear`, a converted old map) and carries a CRC32 of its own content.

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
from dataclasses import asdict, dataclass
from pathlib import Path

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.hashing import sha256_file
from pair_vpr_ros.place_map.dense_codec import CODECS
from pair_vpr_ros.place_map.files import TMP_SUFFIX, remove_quietly, write_bytes_durably

MANIFEST_NAME = "manifest.json"
FORMAT_NAME = "pair_vpr_ros.place_map"
FORMAT_VERSION = 3  # 2: keyframes carry robot and session (issue 22); 3: incremental (34)
READABLE_VERSIONS = (1, 2, 3)  # a version-1 map loads with its keyframes named at load
# Files a save may create; anything else in the directory is left alone.
MAP_FILE_RE = re.compile(
    r"^(index-\d+(-\d+)?\.(faiss|milvus)|(meta|map)-\d+\.sqlite|dense-\d+\.(f16|crc|q4a|q4|p4))"
)
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
    count: int
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

    def content_crc(self) -> int:
        data = asdict(self)
        data.pop("checksum")
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
