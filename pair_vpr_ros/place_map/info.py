"""What a saved place map holds (`pairvpr-map info`): keyframes per robot and session, the model
fingerprint, the index and the size of every file on disk. The map is opened read-only, so every
check of `PlaceMap.load` runs (checksums, counts, schema) and nothing is written."""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from pair_vpr_ros.identity import DEFAULT_ROBOT, LEGACY_SESSION
from pair_vpr_ros.place_map.files import cache_path
from pair_vpr_ros.place_map.manifest import MANIFEST_NAME, read_manifest
from pair_vpr_ros.place_map.place_map import PlaceMap


@dataclass
class SessionInfo:
    """The keyframes of one robot-session in a map: count, first / last id and stamp."""

    robot: str
    session: str
    keyframes: int
    first_id: int
    last_id: int
    first_stamp: float
    last_stamp: float


@dataclass
class MapInfo:
    directory: str
    format_version: int
    keyframes: int
    fingerprint: str
    desc_dim: int
    dense_shape: list[int]
    index: dict[str, Any]  # IndexConfig fields
    dense_codec: str = "f16"  # how the dense tokens are stored (dense_codec.py)
    sessions: list[SessionInfo] = field(default_factory=list)
    with_features: int = 0  # keyframes with stored keypoint features
    represented: int = 0  # keyframes not stored: a stored one represents each (map_growth)
    links: int = 0  # posed loops recorded between stored keyframes
    with_signatures: int = 0  # stored keyframes with an appearance signature
    files: dict[str, int] = field(default_factory=dict)  # file name -> bytes on disk
    notes: list[str] = field(default_factory=list)

    @property
    def total_bytes(self) -> int:
        return sum(self.files.values())

    @property
    def bytes_per_keyframe(self) -> float:
        """Bytes on disk per stored keyframe (0 for an empty map)."""
        return self.total_bytes / self.keyframes if self.keyframes else 0.0

    def to_dict(self) -> dict[str, Any]:
        extra = {"total_bytes": self.total_bytes, "bytes_per_keyframe": self.bytes_per_keyframe}
        return {**asdict(self), **extra}

    def lines(self) -> list[str]:
        """A human-readable report."""
        index = self.index.get("kind", "?")
        out = [
            f"place map {self.directory} (format version {self.format_version})",
            f"keyframes: {self.keyframes} stored ({self.with_features} with features, "
            f"{self.with_signatures} with an appearance signature), {self.represented} "
            f"represented (not stored), {self.links} links",
            f"model fingerprint: {self.fingerprint}",
            f"descriptors: {self.desc_dim}, dense tokens: {self.dense_shape} as "
            f"{self.dense_codec}",
            f"index: {index}",
            "robot/session: keyframes (ids, stamps in s)",
        ]
        out += [
            f"  {s.robot}/{s.session}: {s.keyframes} ({s.first_id}..{s.last_id}, "
            f"{s.first_stamp:.3f}..{s.last_stamp:.3f})"
            for s in self.sessions
        ]
        out.append(f"on disk: {self.total_bytes:,} bytes, {self.bytes_per_keyframe:,.0f} per "
                   "stored keyframe")  # fmt: skip
        out += [f"  {name}: {size:,}" for name, size in sorted(self.files.items())]
        return out + [f"note: {n}" for n in self.notes]


def map_info(directory: str | os.PathLike) -> MapInfo:
    """Open the map in `directory` read-only and describe it (MapError: not a map, damaged).
    A format-1 map's keyframes are reported as robot 'robot', session 'legacy' (with a note),
    the names a load gives them by default."""
    d = Path(directory).expanduser().resolve()
    with PlaceMap.load(d, read_only=True, legacy_identity=(DEFAULT_ROBOT, LEGACY_SESSION)) as m:
        manifest = read_manifest(d)
        info = MapInfo(
            directory=str(d),
            format_version=manifest.format_version,
            keyframes=len(m),
            fingerprint=m.fingerprint,
            desc_dim=m.desc_dim,
            dense_shape=list(m.dense_shape),
            index=asdict(m.index_config),
            dense_codec=manifest.dense_codec,
            sessions=_sessions(m),
            with_features=m.feature_stats()[0],
            notes=[m.load_note] if m.load_note else [],
        )
        counts = m.growth.counts()
        info.represented, info.links = counts.represented, counts.links
        info.with_signatures = counts.signatures
    names = manifest.file_names() | {MANIFEST_NAME}
    if manifest.format_version >= 3:  # and the index snapshot the store names, if any
        names |= {p.name for p in d.iterdir() if p.name.startswith("index-") and p.is_file()}
        cache = cache_path(d / manifest.files["store"]["name"])  # the flat descriptor cache
        names |= {cache.name} if cache.is_file() else set()
    for name in sorted(names):
        info.files[name] = (d / name).stat().st_size
    return info


def _sessions(m: PlaceMap) -> list[SessionInfo]:
    found: dict[tuple[str, str], SessionInfo] = {}
    for meta in m.all_meta():
        s = found.get((meta.robot, meta.session))
        if s is None:
            found[(meta.robot, meta.session)] = SessionInfo(
                meta.robot, meta.session, 1, meta.id, meta.id, meta.stamp, meta.stamp
            )
            continue
        s.keyframes += 1
        s.last_id = meta.id
        s.first_stamp, s.last_stamp = min(s.first_stamp, meta.stamp), max(s.last_stamp, meta.stamp)
    return list(found.values())
