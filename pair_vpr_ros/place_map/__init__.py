"""The keyframe place map: FAISS descriptor index, float16 dense-token store, SQLite metadata.

```python
m = PlaceMap(desc_dim=512, dense_shape=(529, 768), fingerprint=model.fingerprint, index="ivf")
kf_id = m.add(desc, dense, KeyframeMeta(stamp=t, frame_id="cam"))   # ids 0, 1, 2, ...
hits = m.search(desc, k=10, max_id=kf_id - 50)                      # [(id, similarity)]
m.save("maps/site")                                                 # atomic
m = PlaceMap.load("maps/site", expected_fingerprint=model.fingerprint)  # continue mapping
```

A map directory holds `manifest.json` (format_version, generation, count, dims, index settings,
model fingerprint, sha256 + size of the small files), `index-<g>.faiss`, `meta-<g>.sqlite`,
`dense-<g>.crc` (CRC32 per keyframe), the append-only `dense-<h>.f16` ([count, N, D] float16,
possibly longer: bytes past `count` are an unsaved tail) and `map.lock` (writer lock).

Detected on load (MapError naming the file): missing directory/manifest/files, bad JSON, unknown
format version, missing or invalid fields, any change to the index/metadata/CRC files (sha256),
unreadable FAISS index (array sizes beyond the file's are refused before anything is allocated),
a SQLite file of another schema or with values of the wrong type, counts that disagree, a dense
file shorter than `count` or whose first/last entry fails its CRC32 (an edited `dense_shape`).
A load never writes to the saved files (the dense file is never shrunk) and a failed save
deletes what it wrote (also its `*.tmp` files), so a full disk does not stay full.
Detected on read: a damaged dense entry (CRC32, unless verify_dense_reads=False); `load(...,
verify_dense=True)` checks them all up front. Not detected: damage to a dense entry that is only
read while verification is off or that already sits in the in-memory LRU, and memory errors.

A PlaceMap is not thread-safe: callers serialise add/search/save (the pipeline owns one map).
"""

from __future__ import annotations

from pair_vpr_ros.place_map.index import IndexConfig
from pair_vpr_ros.place_map.metadata import KeyframeMeta
from pair_vpr_ros.place_map.place_map import PlaceMap

__all__ = ["IndexConfig", "KeyframeMeta", "PlaceMap"]
