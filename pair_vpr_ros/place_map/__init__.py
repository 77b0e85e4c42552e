"""The keyframe place map: FAISS descriptor index, float16 dense-token store, SQLite metadata.

```python
m = PlaceMap(desc_dim=512, dense_shape=(529, 768), fingerprint=model.fingerprint, index="ivf")
kf_id = m.add(desc, dense, KeyframeMeta(stamp=t, frame_id="cam"))   # ids 0, 1, 2, ...
hits = m.search(desc, k=10, max_id=kf_id - 50)                      # [(id, similarity)]
m.save("maps/site")                                                 # atomic
m = PlaceMap.load("maps/site", expected_fingerprint=model.fingerprint)  # continue mapping
```

A map directory (format 3; docs/map-storage.md) holds `manifest.json` (format_version,
generation, dims, dense codec, index settings, model fingerprint, its own CRC32), the keyframe
store `map-<g>.sqlite` (SQLite in WAL mode: a row per keyframe with its descriptor, dense CRC32
and row CRC32; features; an index snapshot's name for non-flat kinds), the append-only
`dense-<h>.p4` (default: a basis per map), `.q4`, `.q4a` or `.f16`, and `map.lock` (writer
lock). A save commits only the keyframes added since the last one (one SQLite commit); a load
reads the store and the index, dense tokens and features on demand, and copies nothing. Formats 1
and 2 load (legacy.py) and are converted by the next save.

Detected on load (MapError naming the file): missing files, a changed manifest (CRC32), unknown
format version, a damaged or foreign store, a keyframe row failing its CRC32, an index snapshot
failing its CRC32, counts that disagree, a dense file shorter than the rows or whose first/last
entry fails its CRC32. A load never writes to the saved files and a failed save deletes what it
wrote. Detected on read: a damaged dense entry (unless verify_dense_reads=False) or features
row. Not detected: damage to a dense entry only read while verification is off or that already
sits in the in-memory LRU, and memory errors.

A PlaceMap is not thread-safe: callers serialise add/search/save (the pipeline owns one map).
"""

from __future__ import annotations

from pair_vpr_ros.place_map.index import IndexConfig
from pair_vpr_ros.place_map.metadata import KeyframeMeta
from pair_vpr_ros.place_map.place_map import PlaceMap

__all__ = ["IndexConfig", "KeyframeMeta", "PlaceMap"]
