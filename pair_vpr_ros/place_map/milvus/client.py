"""Connecting to Milvus (index kind "milvus"): a milvus-lite file or a server, the token from
the environment, the errors of a connection said in words (a lite file that cannot start, a
locked file, a server that is gone or refuses the token, one too old, a full disk), and
pymilvus's own error logs kept out of the node's log (`quiet`)."""

from __future__ import annotations

import logging
import os
import re
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from pair_vpr_ros.errors import ConfigError, MapError, disk_full

INSTALL = "pip install 'pair_vpr_ros[milvus]' (pymilvus and milvus-lite)"
CONNECT_TIMEOUT_S = 10.0
MIN_SERVER = (2, 3)  # upsert and count(*) queries came with Milvus 2.3
# pymilvus logs every failed call with its traceback, milvus-lite's in-process server too:
# while `quiet`, they do not (our own error or warning says what failed)
_CHATTY = ("pymilvus.decorators", "milvus_lite.adapter.grpc.servicer")


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
    """MapError when `uri`, the milvus-lite file the map in `folder` names, is gone and the map
    is opened `read_only` (connecting would create the file), or is a plain file (milvus-lite
    keeps a folder there: damaged or replaced)."""
    if read_only and is_lite(uri) and not Path(uri).exists():
        raise MapError(
            f"cannot open {where(uri)} of the map in {folder} read-only: it is gone; restore "
            "it, or open the map writable to insert its keyframes again"
        )
    if is_lite(uri) and Path(uri).is_file():
        raise MapError(
            f"cannot open {where(uri)} of the map in {folder}: it is a plain file, not "
            "milvus-lite's data (a folder of that name): damaged or replaced; the map itself is "
            "intact: move the file away and load the map writable once, which inserts its "
            "keyframes again from the map's own copy"
        )


@contextmanager
def quiet() -> Iterator[None]:
    """pymilvus's and milvus-lite's own error logs (each a traceback) off while entered."""
    loggers = [logging.getLogger(name) for name in _CHATTY]
    was = [log.disabled for log in loggers]
    for log in loggers:
        log.disabled = True
    try:
        yield
    finally:
        for log, before in zip(loggers, was, strict=True):
            log.disabled = before


def full_disk(err: BaseException, uri: str) -> str:
    """'' unless `err` says the disk of `uri` is full; else how to say so."""
    if not disk_full(err):
        return ""
    there = "its disk" if is_lite(uri) else "the server's disk"
    return f"{there} is full ({_reason(err)})"


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
        with lite, quiet():
            client = milvus.MilvusClient(uri, token=token, timeout=CONNECT_TIMEOUT_S)
            version = "" if is_lite(uri) else str(client.get_server_version())
    except Exception as err:  # pymilvus raises MilvusException and its subclasses
        full = full_disk(RuntimeError(f"{lite.reason} {_reason(err)}"), uri)
        if full:
            raise MapError(
                f"cannot open {where(uri)}: {full}: free disk space there, or set milvus_uri "
                "to a disk with room"
            ) from err
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
