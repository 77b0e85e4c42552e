"""Helpers of the bad-input matrix (test/*/test_bad_input_*.py): digests that prove nothing
saved changed, and files that are not what their name says."""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
from pathlib import Path
from urllib.parse import quote

from pair_vpr_ros.place_map.dense_codec import entry_bytes, head_bytes

LOCK_NAME = "map.lock"  # holds the pid of the last writer: not part of the saved map


def tree_digest(root: Path) -> dict[str, str]:
    """{relative path: sha256} of every regular file under `root` (map.lock left out)."""
    out = {}
    for path in sorted(Path(root).rglob("*")):
        if path.is_file() and path.name != LOCK_NAME:
            out[str(path.relative_to(root))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def make_fifo(path: Path) -> Path:
    """A named pipe at `path`: opening it for reading blocks until a writer comes."""
    os.mkfifo(path)
    return path


def _store_rows(path: Path) -> tuple[int, str]:
    """(keyframe rows, sha256 of every row) of a format-3 keyframe store, read through SQLite:
    what a save committed, not the bytes of its file (a writable load opens its WAL)."""
    immutable = "" if Path(f"{path}-wal").exists() else "&immutable=1"  # else it leaves a -wal
    conn = sqlite3.connect(f"file:{quote(str(path))}?mode=ro{immutable}", uri=True)
    digest = hashlib.sha256()
    for table in ("keyframes", "features", "state"):
        for row in conn.execute(f"SELECT * FROM {table} ORDER BY 1"):
            digest.update(repr(row).encode())
    count = conn.execute("SELECT COUNT(*) FROM keyframes").fetchone()[0]
    conn.close()
    return count, digest.hexdigest()


def saved_map_digest(directory: Path) -> dict[str, str]:
    """sha256 of what a saved map consists of: its manifest, the files it names, and of the
    dense file only the `count` entries it lists (later bytes are a live map's unsaved appends,
    which the format allows); format 3: the store's rows."""
    directory = Path(directory)
    manifest = json.loads((directory / "manifest.json").read_text())
    out = {"manifest.json": hashlib.sha256((directory / "manifest.json").read_bytes()).hexdigest()}
    if manifest["format_version"] >= 3:
        count, out["store"] = _store_rows(directory / manifest["files"]["store"]["name"])
        shape, codec = manifest["dense_shape"], manifest["dense_codec"]
        size = head_bytes(shape, codec) + count * entry_bytes(shape, codec)
        data = (directory / manifest["files"]["dense"]["name"]).read_bytes()[:size]
        out["dense"] = hashlib.sha256(data).hexdigest()
        return out
    for role, entry in manifest["files"].items():
        data = (directory / entry["name"]).read_bytes()
        if role == "dense":
            n, d = manifest["dense_shape"]
            data = data[: manifest["count"] * n * d * 2]
        out[entry["name"]] = hashlib.sha256(data).hexdigest()
    return out


class FlakyClient:
    """A MilvusClient stand-in that forwards to a real one until `down` is set; then every call
    raises what pymilvus raises for a server that cannot be reached. `lose_replies`: calls
    reach the server, but their answers are lost (the same error after the work is done)."""

    def __init__(self, client) -> None:
        self._client, self.down, self.lose_replies, self.calls = client, False, False, 0
        self.names: list[str] = []  # the methods called, in order

    def __getattr__(self, name: str):
        real = getattr(self._client, name)

        def call(*args, **kwargs):
            self.calls += 1
            self.names.append(name)
            if self.lose_replies:
                real(*args, **kwargs)
            if self.down or self.lose_replies:
                import pymilvus  # only the milvus tests use this

                raise pymilvus.MilvusException(
                    code=2, message="Fail connecting to server on 127.0.0.1:19530"
                )
            return real(*args, **kwargs)

        return call


def make_flaky(place_map) -> FlakyClient:
    """Swap the client of a "milvus" PlaceMap for a FlakyClient around it."""
    index = place_map._index
    index.client = FlakyClient(index.client)
    return index.client


def store_text(config) -> str:
    """How messages name the store of `config` (written out here, not taken from the code)."""
    uri = config.milvus_uri
    return f"milvus-lite file {uri}" if uri.endswith(".db") else f"Milvus server {uri}"
