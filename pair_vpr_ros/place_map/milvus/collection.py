"""Creating or checking the keyframe collection of index kind "milvus" (client.py connects).

The collection: `pk` INT64 primary key (`writer << 32 | keyframe id`, see expr.py),
`robot` and `session` VARCHAR, `stamp` DOUBLE (s), `desc` FLOAT_VECTOR of the model's
dimension, inner-product metric, Strong consistency (a row inserted is seen by the next search).
The model fingerprint is a collection property (`pairvpr.fingerprint`): milvus-lite returns the
schema description empty, properties come back. A collection of another model, of another
dimension or of another layout is refused.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path
from typing import Any

from pair_vpr_ros.errors import ConfigError, MapError, MapFingerprintError
from pair_vpr_ros.place_map.milvus.client import (
    _reason,
    full_disk,
    is_lite,
    pymilvus,
    quiet,
    where,
)

FINGERPRINT_KEY = "pairvpr.fingerprint"
FORMAT_KEY = "pairvpr.format"
FORMAT = "pair_vpr_ros.keyframes.v1"
FIELDS = ("pk", "robot", "session", "stamp", "desc")
NAME_MAX = 256  # VARCHAR length of robot and session

MILVUS_INDEXES = ("IVF_FLAT", "HNSW", "FLAT")
MILVUS_CONSISTENCY = ("Bounded", "Session", "Strong")  # docs/milvus.md: what each costs
MILVUS_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,254}")  # Milvus's collection-name rule


def check_milvus_settings(config: Any) -> str:
    """ConfigError unless an IndexConfig's milvus_* settings are usable -> its milvus_uri, a
    lite file's made absolute (the record of a saved map must not depend on the cwd)."""
    uri = config.milvus_uri
    if not isinstance(uri, str) or not (
        uri.endswith(".db") or re.fullmatch(r"https?://[^\s/]+(:\d+)?/?", uri)
    ):
        raise ConfigError(
            f"milvus_uri must be a milvus-lite file (a path ending in .db) or a Milvus "
            f"server address (http://host:19530), got {uri!r}"
        )
    if not isinstance(config.milvus_collection, str) or not MILVUS_NAME_RE.fullmatch(
        config.milvus_collection
    ):
        raise ConfigError(
            f"milvus_collection must be 1-255 letters, digits or underscores, not starting "
            f"with a digit, got {config.milvus_collection!r}"
        )
    if config.milvus_index not in MILVUS_INDEXES:
        raise ConfigError(
            f"milvus_index must be one of {MILVUS_INDEXES}, got {config.milvus_index!r}"
        )
    if config.milvus_consistency not in MILVUS_CONSISTENCY:
        raise ConfigError(
            f"milvus_consistency must be one of {MILVUS_CONSISTENCY}, got "
            f"{config.milvus_consistency!r}"
        )
    if not isinstance(config.milvus_token_env, str):
        raise ConfigError(f"milvus_token_env must be a string, got {config.milvus_token_env!r}")
    return str(Path(uri).expanduser().absolute()) if uri.endswith(".db") else uri


def open_collection(
    client: Any, uri: str, name: str, dim: int, fingerprint: str, index: dict
) -> str:
    """Create collection `name` (empty, with `index` = add_index keyword arguments) or check the
    one there; either way it is loaded for search -> its vector index type (a collection made
    earlier keeps the type it was made with, whatever `index` says)."""
    milvus = pymilvus()
    try:
        with quiet():
            if not client.has_collection(name):
                try:
                    _create(client, milvus, name, dim, fingerprint, index)
                except milvus.MilvusException:
                    if not client.has_collection(name):
                        raise
                    # another writer made it meanwhile (two robots starting at once): check it
            if client.has_collection(name):
                check_collection(client.describe_collection(name), uri, name, dim, fingerprint)
            ensure_loaded(client, name)
            return str(client.describe_index(name, "desc").get("index_type", index["index_type"]))
    except milvus.MilvusException as err:
        full = full_disk(err, uri)
        if full:
            raise MapError(
                f"cannot open collection {name!r} in {where(uri)}: {full}: free disk space "
                "there, or set milvus_uri to a disk with room"
            ) from err
        advice = (  # a lite file has no server and no token
            "its data may be damaged (e.g. left half written by a full disk): move it away, or "
            "set milvus_uri to a new file" if is_lite(uri) else
            "check that the server runs and that the token allows it"
        )  # fmt: skip
        raise MapError(
            f"cannot open collection {name!r} in {where(uri)} ({_reason(err)}): {advice}"
        ) from err


def ensure_loaded(client: Any, name: str) -> None:
    """Load collection `name` for search and query (a re-opened lite file comes back released)."""
    if str(client.get_load_state(name).get("state")) != "Loaded":
        client.load_collection(name)


def _create(client: Any, milvus: Any, name: str, dim: int, fingerprint: str, index: dict):
    dtype = milvus.DataType
    schema = client.create_schema(auto_id=False, enable_dynamic_field=False)
    schema.add_field("pk", dtype.INT64, is_primary=True)
    schema.add_field("robot", dtype.VARCHAR, max_length=NAME_MAX)
    schema.add_field("session", dtype.VARCHAR, max_length=NAME_MAX)
    schema.add_field("stamp", dtype.DOUBLE)
    schema.add_field("desc", dtype.FLOAT_VECTOR, dim=int(dim))
    params = client.prepare_index_params()
    params.add_index("desc", metric_type="IP", **index)
    # milvus-lite's in-process server logs a traceback for a call it lacks (AllocTimestamp)
    # while pymilvus waits for the new index; creation succeeds, so keep that out of the log.
    quiet = logging.getLogger("grpc._server")
    was, quiet.disabled = quiet.disabled, True
    try:
        client.create_collection(
            name,
            schema=schema,
            index_params=params,
            consistency_level="Strong",
            properties={FINGERPRINT_KEY: json.dumps(fingerprint), FORMAT_KEY: FORMAT},
        )
    finally:
        quiet.disabled = was


def check_collection(info: dict, uri: str, name: str, dim: int, fingerprint: str) -> None:
    """MapError unless `info` (describe_collection) is a keyframe collection of `dim`-d
    descriptors made by the model `fingerprint` (MapFingerprintError when another model)."""
    place = f"collection {name!r} in {where(uri)}"
    fields = check_layout(info, place)
    props = info.get("properties") or {}
    have = int(fields["desc"].get("params", {}).get("dim", -1))
    if have != int(dim):
        raise MapError(
            f"{place} holds {have}-d descriptors, this map's are {dim}-d: use another "
            "milvus_collection for this model"
        )
    stored = props.get(FINGERPRINT_KEY)
    try:
        stored = json.loads(stored)
    except (TypeError, ValueError):
        stored = repr(stored)
    if stored != fingerprint:
        raise MapFingerprintError(
            f"{place} holds descriptors of model {stored!r}, this map's model is "
            f"{fingerprint!r}: use the same weights and image size, or another milvus_collection"
        )


def check_layout(info: dict, place: str) -> dict:
    """MapError unless `info` (describe_collection of `place`) has this package's keyframe
    layout -> its fields by name."""
    props = info.get("properties") or {}
    fields = {f["name"]: f for f in info.get("fields", [])}
    if props.get(FORMAT_KEY) != FORMAT or tuple(fields) != FIELDS:
        raise MapError(
            f"{place} is not a pair_vpr_ros keyframe collection (fields {list(fields)}, format "
            f"{props.get(FORMAT_KEY)!r}; expected fields {list(FIELDS)}): set milvus_collection "
            "to a new name or to one this package made"
        )
    return fields


def index_params(config) -> dict:
    """add_index arguments of `config.milvus_index` (see docs/milvus.md for the choice)."""
    kind = config.milvus_index
    if kind == "HNSW":
        params = {"M": config.hnsw_m, "efConstruction": config.ef_construction}
        return dict(index_type="HNSW", params=params)
    if kind == "IVF_FLAT":
        return dict(index_type="IVF_FLAT", params={"nlist": config.nlist or 1024})
    return dict(index_type="FLAT", params={})


def search_params(config, k: int, index_type: str) -> dict:
    if index_type == "HNSW":
        return {"params": {"ef": max(int(config.ef_search), int(k))}}
    if index_type == "IVF_FLAT":
        return {"params": {"nprobe": int(config.nprobe)}}
    return {"params": {}}
