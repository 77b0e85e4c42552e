"""What a saved map opens into (`MapParts`, `SavedCrcs`) and the checks both loaders share: the
current format's (persist.py) and formats 1-2's (legacy.py), so neither loader imports the
other's."""

from __future__ import annotations

from array import array
from dataclasses import dataclass, replace
from pathlib import Path

from pair_vpr_ros.errors import ConfigError, MapError
from pair_vpr_ros.place_map.dense_store import DenseStore
from pair_vpr_ros.place_map.index import DescriptorIndex, IndexConfig
from pair_vpr_ros.place_map.manifest import Manifest
from pair_vpr_ros.place_map.store import KeyframeStore


@dataclass
class MapParts:
    """The live stores of a map, as a save writes them and `open_saved` returns them."""

    index: DescriptorIndex  # or a MilvusIndex (kind "milvus")
    store: KeyframeStore
    dense: DenseStore
    desc_dim: int
    dense_shape: tuple[int, int]
    fingerprint: str
    format_version: int = 3  # of the save it was opened from (1, 2: converted by the next save)
    note: str = ""  # what the loader should log (an old format, keyframes named at load)
    generation: int = 0
    desc_cache: tuple[int, int] | None = None  # (count, CRC32) of the flat descriptor cache
    manifest: Manifest | None = None  # format 3+: the record a save writes again


def check_count(index: DescriptorIndex, count: int, path: Path) -> DescriptorIndex:
    if len(index) != count:
        raise MapError(
            f"FAISS index {path} holds {len(index)} vectors, the map lists {count} keyframes: "
            "the map is damaged, restore it from a backup or rebuild it"
        )
    return index


def index_config(m: Manifest, ef_search: int | None) -> IndexConfig:
    """The saved index settings; the dense codec is the manifest's (old maps: f16)."""
    try:
        config = replace(IndexConfig(**m.index), dense_codec=m.dense_codec)
        return config if ef_search is None else replace(config, ef_search=int(ef_search))
    except (TypeError, ConfigError) as err:
        raise MapError(f"manifest index settings {m.index} are invalid ({err}): rebuild") from err


class SavedCrcs:
    """The dense CRC32s of a loaded map (DenseStore.crcs): the saved ones read from the store
    when an entry is read (a load reads none), those of entries added since kept here."""

    def __init__(self, lookup, saved: int) -> None:
        self._lookup, self._saved, self._new = lookup, int(saved), array("I")

    def __len__(self) -> int:
        return self._saved + len(self._new)

    def __getitem__(self, i: int) -> int:
        i = i + len(self) if i < 0 else i
        return self._new[i - self._saved] if i >= self._saved else self._lookup(i)

    def append(self, crc: int) -> None:
        self._new.append(crc)

    def pop(self) -> int:
        if self._new:
            return self._new.pop()
        self._saved -= 1
        return self._lookup(self._saved)

    def materialised(self) -> array:
        return array("I", (self[i] for i in range(len(self))))
