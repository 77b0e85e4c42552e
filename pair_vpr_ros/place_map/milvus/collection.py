"""Connecting to Milvus and creating or checking the keyframe collection (index kind "milvus").

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
import os
import re
import socket
from pathlib import Path
from typing import Any

from pair_vpr_ros.errors import ConfigError, MapError, MapFingerprintError

FINGERPRINT_KEY = "pairvpr.fingerprint"
FORMAT_KEY = "pairvpr.format"
FORMAT = "pair_vpr_ros.keyframes.v1"
FIELDS = ("pk", "robot", "session", "stamp", "desc")
NAME_MAX = 256  # VARCHAR length of robot and session
INSTALL = "pip install 'pair_vpr_ros[milvus]' (pymilvus and milvus-lite)"
CONNECT_TIMEOUT_S = 10.0
MIN_SERVER = (2, 3)  # upsert and count(*) queries came with Milvus 2.3

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


def pymilvus() -> Any:
    """The pymilvus module, or a ConfigError saying what to install."""
    try:
        import pymilvus as module
    except ImportError as err:
        raise ConfigError(
            f"place map index 'milvus' needs the optional packages pymilvus and milvus-lite, "
            f"which are not installed ({err}): {INSTALL}"
        ) from err
    return module


def is_lite(uri: str) -> bool:
    return uri.endswith(".db")


def where(uri: str) -> str:
    """The URI as messages show it (a server address without any user:password part)."""
    if is_lite(uri):
        return f"milvus-lite file {uri}"
    scheme, _, rest = uri.partition("://")
    return f"Milvus server {scheme}://{rest.rpartition('@')[2]}"


def is_lite_folder(path: Path) -> bool:
    """`path` holds milvus-lite's data (its LOCK file and collections folder)."""
    return (path / "LOCK").is_file() and (path / "collections").is_dir()


def check_lite_exists(uri: str, folder: Path, read_only: bool) -> None:
    """MapError when `uri` is a milvus-lite file that is gone and the map in `folder` is opened
    `read_only` (connecting would create the file)."""
    if read_only and is_lite(uri) and not Path(uri).exists():
        raise MapError(
            f"cannot open {where(uri)} of the map in {folder} read-only: it is gone; restore "
            "it, or open the map writable to insert its keyframes again"
        )


def connect(uri: str, token_env: str) -> Any:
    """A MilvusClient for `uri` (a milvus-lite file is created if missing); the token, if any,
    comes from the environment variable `token_env` and is never logged or stored."""
    milvus = pymilvus()
    if is_lite(uri) and not Path(uri).parent.is_dir():
        raise MapError(
            f"cannot open {where(uri)}: its folder {Path(uri).parent} does not exist; create it "
            "or set milvus_uri to a path in an existing folder"
        )
    if is_lite(uri) and Path(uri).exists() and not Path(uri).is_dir():
        raise MapError(
            f"cannot open {where(uri)}: it is a plain file, but milvus-lite keeps its data in a "
            "folder of that name; set milvus_uri to the path the maps were made with or to a new "
            "one"
        )
    if (
        is_lite(uri)
        and Path(uri).is_dir()
        and not is_lite_folder(Path(uri))
        and any(Path(uri).iterdir())
    ):
        raise MapError(
            f"cannot open {where(uri)}: it is a folder of other files, not milvus-lite's data; "
            "set milvus_uri to the path the maps were made with or to a new one"
        )
    token = os.environ.get(token_env, "") if token_env else ""
    lite = _LiteReason()  # milvus-lite logs its own traceback: its reason goes in our message
    try:
        with lite:
            client = milvus.MilvusClient(uri, token=token, timeout=CONNECT_TIMEOUT_S)
        version = "" if is_lite(uri) else str(client.get_server_version())
    except Exception as err:  # pymilvus raises MilvusException and its subclasses
        if lite.reason and not lite.reason.startswith("DataDirLockedError"):  # lock: below
            raise MapError(
                f"cannot open {where(uri)}: milvus-lite cannot start on it ({lite.reason}); "
                "set milvus_uri to a path in a writable folder"
            ) from err
        hint = (
            f"check milvus_uri, that the server runs and can be reached, and the token in "
            f"${token_env}"
        )
        if not is_lite(uri) and answers(uri):  # it runs: pymilvus says the same for a bad token
            given = f"the token in ${token_env}" if token else f"no token (${token_env} is unset)"
            raise MapError(
                f"{where(uri)} answers but refused the connection with {given} "
                f"({_reason(err)}): a server with authorization needs a valid 'user:password' "
                f"or API key in ${token_env}; check it (and that milvus_uri is a Milvus server)"
            ) from err
        if is_lite(uri):  # pymilvus drops milvus-lite's reason; its file lock is the usual one
            hint = (
                "milvus-lite lets one process open a file at a time: if another process holds "
                "it, stop that process, use another file, or run a Milvus server for several "
                "writers"
            )
        raise MapError(f"cannot connect to {where(uri)} ({_reason(err)}): {hint}") from err
    check_version(version, uri)
    return client


def answers(uri: str) -> bool:
    """Something accepts TCP connections at the server address `uri` (within 2 s)."""
    rest = uri.partition("://")[2].rpartition("@")[2].rstrip("/")
    host, _, port = rest.rpartition(":")
    default = 443 if uri.startswith("https") else 19530
    try:
        with socket.create_connection((host or rest, int(port) if host else default), 2.0):
            return True
    except (OSError, ValueError):
        return False


def check_version(version: str, uri: str) -> None:
    """MapError when the server is older than MIN_SERVER (no upsert, no count(*) there)."""
    found = re.match(r"v?(\d+)\.(\d+)", version)
    if found and (int(found[1]), int(found[2])) < MIN_SERVER:
        raise MapError(
            f"{where(uri)} runs Milvus {version}, this package needs Milvus "
            f"{'.'.join(map(str, MIN_SERVER))} or newer (upsert, count(*)): upgrade the server"
        )


class _LiteReason(logging.Handler):
    """While entered: milvus-lite's server manager logs to this handler only (not stderr);
    `reason` is the error of the traceback it logged, e.g. "PermissionError: ..."."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.reason = ""
        self._log = logging.getLogger("milvus_lite.server_manager")

    def emit(self, record: logging.LogRecord) -> None:
        err = record.exc_info[1] if record.exc_info else None
        self.reason = f"{type(err).__name__}: {err}" if err else record.getMessage()

    def __enter__(self) -> _LiteReason:
        self._was = self._log.propagate
        self._log.propagate = False
        self._log.addHandler(self)
        return self

    def __exit__(self, *exc: object) -> None:
        self._log.removeHandler(self)
        self._log.propagate = self._was


def _reason(err: BaseException) -> str:
    return str(getattr(err, "message", "") or err)[:200]


def open_collection(
    client: Any, uri: str, name: str, dim: int, fingerprint: str, index: dict
) -> str:
    """Create collection `name` (empty, with `index` = add_index keyword arguments) or check the
    one there; either way it is loaded for search -> its vector index type (a collection made
    earlier keeps the type it was made with, whatever `index` says)."""
    milvus = pymilvus()
    try:
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
        raise MapError(
            f"cannot open collection {name!r} in {where(uri)} ({_reason(err)}): check that the "
            "server runs and that the token allows it"
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
