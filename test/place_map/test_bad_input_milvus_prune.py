"""Bad-input matrix, `pairvpr-map prune-milvus`: every bad input is one `error:` line and exit
code 1, no row is removed, no map folder changes and no milvus-lite file is created."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from bad_input import make_flaky, tree_digest
from extras import require
from map_fixtures import DENSE, DIM, make_map
from test_bad_input_milvus import URI_RULE

from pair_vpr_ros.offline.map_cli import main
from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap

require("pymilvus")


def _rows(uri: str, collection: str = "kf") -> int:
    from pymilvus import MilvusClient

    client = MilvusClient(uri)
    found = client.query(collection, filter="pk >= 0", output_fields=["count(*)"])
    return int(found[0]["count(*)"])


@pytest.fixture
def site(tmp_path) -> str:
    """maps/site.db, collection kf: a saved map of 3 keyframes and 2 stale rows."""
    uri = str(tmp_path / "maps" / "site.db")
    config = IndexConfig(kind="milvus", milvus_uri=uri, milvus_collection="kf")
    (tmp_path / "maps").mkdir()
    make_map(tmp_path / "maps" / "a", "r1", "mon", 3, seed=1, index=config)
    with PlaceMap(DIM, DENSE, "model-a", index=config) as m:  # never saved
        for i in range(2):
            m.add(np.ones(DIM), np.zeros(DENSE), KeyframeMeta(stamp=float(i)))
        make_flaky(m).down = True  # Milvus gone at close (or a crash): its rows stay
    return uri


def _other_program(t: Path, site: str) -> list[str]:
    from pymilvus import MilvusClient

    MilvusClient(site).create_collection("other", dimension=DIM)  # id + vector, no format
    return [site, "--collection", "other"]


def _damaged(t: Path, site: str) -> list[str]:
    (t / "maps" / "a" / "index-1-0.milvus").write_bytes(b"x")
    return [site]


CASES = {
    # name: (builder of the arguments before --maps, error text after "error: ")
    "missing file": (
        lambda t, s: [str(t / "none.db")],
        "milvus-lite file {t}/none.db does not exist: give the file the maps were made with "
        "(their milvus_uri)",
    ),
    "plain file": (
        lambda t, s: [str((t / "x.db").write_text("hello") and t / "x.db")],
        "cannot open milvus-lite file {t}/x.db: it is a plain file, but milvus-lite keeps its "
        "data in a folder of that name; set milvus_uri to the path the maps were made with or to "
        "a new one",
    ),
    "folder not milvus-lite": (
        lambda t, s: [str((t / "y.db").mkdir() or t / "y.db")],
        "{t}/y.db is not a milvus-lite file (no LOCK file and collections folder in it): give the "
        "file the maps were made with (their milvus_uri)",
    ),
    "not a uri": (lambda t, s: ["maps.sqlite"], URI_RULE.format("maps.sqlite")),
    "bad collection name": (
        lambda t, s: [s, "--collection", "1kf"],
        "milvus_collection must be 1-255 letters, digits or underscores, not starting with a "
        "digit, got '1kf'",
    ),
    "no such collection": (
        lambda t, s: [s, "--collection", "nope"],
        "collection 'nope' in milvus-lite file {s} does not exist (collections there: ['kf']): "
        "give --collection the maps' milvus_collection",
    ),
    "collection of another program": (
        _other_program,
        "collection 'other' in milvus-lite file {s} is not a pair_vpr_ros keyframe collection "
        "(fields ['id', 'vector'], format None; expected fields ['pk', 'robot', 'session', "
        "'stamp', 'desc']): set milvus_collection to a new name or to one this package made",
    ),
    "damaged map": (
        _damaged,
        "saved map {t}/maps/a cannot be read (index snapshot {t}/maps/a/index-1-0.milvus fails "
        "its CRC32 check",
    ),
    "server unreachable": (
        lambda t, s: ["http://127.0.0.1:9"],
        "cannot connect to Milvus server http://127.0.0.1:9 (Fail connecting to server on "
        "127.0.0.1:9, illegal connection params or server unavailable): check milvus_uri, that "
        "the server runs and can be reached, and the token in $PAIRVPR_MILVUS_TOKEN",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_prune_is_an_error_line_and_removes_nothing(tmp_path, capsys, site, case):
    build, message = CASES[case]
    args = build(tmp_path, site)
    before = tree_digest(tmp_path / "maps" / "a")
    assert main(["prune-milvus", *args, "--maps", str(tmp_path / "maps"), "--yes"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: " + message.format(t=tmp_path, s=site)) and err.count("\n") == 1
    assert tree_digest(tmp_path / "maps" / "a") == before
    assert _rows(site) == 5  # 3 saved + 2 stale: nothing removed
    assert not (tmp_path / "none.db").exists()


def test_a_missing_maps_folder(tmp_path, capsys, site):
    assert main(["prune-milvus", site, "--maps", str(tmp_path / "nowhere"), "--yes"]) == 1
    assert capsys.readouterr().err == (
        f"error: --maps {tmp_path / 'nowhere'} does not exist or is not a folder\n"
    )
    assert _rows(site) == 5


def test_a_lite_file_another_process_holds(tmp_path, capsys):
    """milvus-lite lets one process open a file: prune says so and changes nothing."""
    db = tmp_path / "held.db"
    code = (
        "import sys, time\nfrom pymilvus import MilvusClient\n"
        f"c = MilvusClient({str(db)!r})\nc.create_collection('kf', dimension=4)\n"
        "print('ready', flush=True)\nsys.stdin.readline()\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        (tmp_path / "maps").mkdir()
        assert main(["prune-milvus", str(db), "--maps", str(tmp_path / "maps"), "--yes"]) == 1
        assert capsys.readouterr().err == (
            f"error: cannot connect to milvus-lite file {db} (Open local milvus failed): "
            "milvus-lite lets one process open a file at a time: if another process holds it, "
            "stop that process, use another file, or run a Milvus server for several writers\n"
        )
    finally:
        proc.communicate("\n", timeout=60)
