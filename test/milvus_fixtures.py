"""Fixtures of the "milvus" place-map tests, provided to every test by test/conftest.py: every
test that takes `milvus` runs twice, on a milvus-lite file (one per test module: its start takes
~1 s) and on a Milvus server, each time in a collection no other test uses. Where the milvus
extra is not installed both skip (fail under CI).

The server is the one at $PAIRVPR_MILVUS_TEST_URI (default http://127.0.0.1:19530; start one
with `scripts/milvus_server.sh start`). When none answers, the server variants are skipped with
the reason, except under CI=true, where they fail: CI starts the server (.ci/run) and must not
pass without having tested it."""

from __future__ import annotations

import itertools
import os
import urllib.request
from pathlib import Path

import pytest
from extras import require

from pair_vpr_ros.place_map import IndexConfig

SERVER_URI = os.environ.get("PAIRVPR_MILVUS_TEST_URI", "http://127.0.0.1:19530")
HEALTH_URL = os.environ.get("PAIRVPR_MILVUS_TEST_HEALTH", "http://127.0.0.1:9091/healthz")
_names = itertools.count()
_health: list[str] = []  # the reason a server is unusable ("" = usable), checked once


def server_problem() -> str:
    """ "" when the test server answers its health check, else why not (checked once)."""
    if not _health:
        try:
            with urllib.request.urlopen(HEALTH_URL, timeout=3) as reply:
                body = reply.read().decode(errors="replace").strip()
            _health.append("" if body == "OK" else f"{HEALTH_URL} says {body!r}")
        except OSError as err:
            _health.append(f"no Milvus server answers {HEALTH_URL} ({err})")
    return _health[0]


def need_server() -> str:
    """The test server's URI; skips the test (fails it under CI=true) when none answers."""
    problem = server_problem()
    if problem:
        hint = "start one with scripts/milvus_server.sh start"
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true needs the Milvus test server: {problem}; {hint}")
        pytest.skip(f"{problem}: {hint}")
    return SERVER_URI


def new_name(prefix: str = "kf") -> str:
    """A collection name no other test (nor another test run on the same server) uses."""
    return f"{prefix}_{os.getpid()}_{next(_names)}"


def drop(uri: str, name: str) -> None:
    """Remove a test's collection from the server (a lite file goes with tmp_path)."""
    client = require("pymilvus").MilvusClient(uri)
    try:
        client.drop_collection(name)
    finally:
        client.close()


@pytest.fixture(scope="module")
def lite_db(tmp_path_factory) -> Path:
    require("pymilvus")
    require("milvus_lite")
    return tmp_path_factory.mktemp("milvus") / "maps.db"


@pytest.fixture(params=["lite", "server"])
def store(request, lite_db: Path) -> str:
    """The milvus_uri of one kind of store: a milvus-lite file or the test server."""
    return str(lite_db) if request.param == "lite" else need_server()


@pytest.fixture
def milvus(store: str):
    """An IndexConfig of a collection no other test uses (exact FLAT: results comparable)."""
    name = new_name()
    yield IndexConfig(kind="milvus", milvus_uri=store, milvus_collection=name, milvus_index="FLAT")
    if not store.endswith(".db"):
        drop(store, name)
        drop(store, name + "_x")  # a second collection some tests make beside it


@pytest.fixture
def server_milvus():
    """As `milvus`, on the test server only (server-only behaviour: faults, two processes)."""
    name = new_name()
    uri = need_server()
    yield IndexConfig(kind="milvus", milvus_uri=uri, milvus_collection=name, milvus_index="FLAT")
    drop(uri, name)
