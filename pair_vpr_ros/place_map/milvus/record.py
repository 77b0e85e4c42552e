"""The record of a "milvus" index in its map folder (`index-<g>-<k>.milvus`, index.py): where
its rows live (URI, collection), its writer key, and the map's own copy of what it inserted
(descriptors, robot, session, stamp of every keyframe), checked against the manifest at load."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map.milvus.expr import MAX_WRITER

RECORD_FORMAT = "pair_vpr_ros.milvus_record.v1"


def write_record(path: Path, index, desc: np.ndarray, rows: list) -> None:
    """Write the record of `index` (a MilvusIndex) with its copy: desc [n, dim] float32 and
    rows (robot, session, stamp) each."""
    n = len(rows)
    record = dict(format=RECORD_FORMAT, uri=index.uri, collection=index.collection,
                  writer=index.writer, dim=index.dim, count=n)  # fmt: skip
    robots, sessions, stamps = [list(c) for c in zip(*rows, strict=True)] or [[]] * 3
    buf = io.BytesIO()
    np.savez(
        buf, record=np.array(json.dumps(record)), desc=desc,
        stamps=np.array(stamps, np.float64).reshape(n), robots=np.array(robots, str),
        sessions=np.array(sessions, str),
    )  # fmt: skip
    Path(path).write_bytes(buf.getvalue())


def read_record(path: Path, dim: int, count: int) -> tuple[dict, dict]:
    """The record file written by `MilvusIndex.write`, checked against the manifest."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
        record = json.loads(str(arrays.pop("record")))
        ok = record.get("format") == RECORD_FORMAT and record.get("count") == count
        ok = ok and record.get("dim") == dim and 0 < int(record.get("writer", 0)) <= MAX_WRITER
        ok = ok and arrays["desc"].shape == (count, dim)
        ok = ok and all(len(arrays[k]) == count for k in ("stamps", "robots", "sessions"))
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as err:
        raise MapError(f"milvus record {path} cannot be read ({err}): the map is damaged") from err
    if not ok:
        raise MapError(
            f"milvus record {path} does not match the manifest ({count} keyframes of {dim}-d): "
            "the map is damaged, restore it from a backup or rebuild it"
        )
    return record, arrays
