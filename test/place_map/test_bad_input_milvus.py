"""Bad-input matrix, index kind "milvus": wrong URIs and names are ConfigErrors, unreachable
servers, collections of another dimension, model or layout and damaged records are MapErrors
with exact texts; a server that goes away is a counted skip; nothing saved changes."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from bad_input import make_flaky, store_text, tree_digest
from test_bad_input_map_store import resign_manifest
from test_place_map_persist import DIM, SHAPE, add_range, dense_for, desc_for, meta_for

from pair_vpr_ros.errors import ConfigError, MapError, MapFingerprintError, MapUnavailableError
from pair_vpr_ros.place_map import IndexConfig, PlaceMap
from pair_vpr_ros.place_map.milvus.record import read_record

URI_RULE = (
    "milvus_uri must be a milvus-lite file (a path ending in .db) or a Milvus server address "
    "(http://host:19530), got {!r}"
)
BAD_CONFIGS = {
    "no uri": (dict(milvus_uri=""), URI_RULE.format("")),
    "sqlite file": (dict(milvus_uri="maps/x.sqlite"), URI_RULE.format("maps/x.sqlite")),
    "ftp": (dict(milvus_uri="ftp://host:19530"), URI_RULE.format("ftp://host:19530")),
    "no scheme": (dict(milvus_uri="localhost:19530"), URI_RULE.format("localhost:19530")),
    "no host": (dict(milvus_uri="http://"), URI_RULE.format("http://")),
    "uri not text": (dict(milvus_uri=5), URI_RULE.format(5)),
    "collection digit": (
        dict(milvus_collection="1map"),
        "milvus_collection must be 1-255 letters, digits or underscores, not starting with a "
        "digit, got '1map'",
    ),
    "collection dash": (
        dict(milvus_collection="my-map"),
        "milvus_collection must be 1-255 letters, digits or underscores, not starting with a "
        "digit, got 'my-map'",
    ),
    "consistency": (
        dict(milvus_consistency="Eventually"),
        "milvus_consistency must be one of ('Bounded', 'Session', 'Strong'), got 'Eventually'",
    ),
    "milvus index": (
        dict(milvus_index="IVF_PQ"),
        "milvus_index must be one of ('IVF_FLAT', 'HNSW', 'FLAT'), got 'IVF_PQ'",
    ),
}


@pytest.mark.parametrize("case", list(BAD_CONFIGS))
def test_bad_milvus_settings_are_config_errors(case: str) -> None:
    fields, message = BAD_CONFIGS[case]
    settings = {"kind": "milvus", "milvus_uri": "/tmp/x.db", **fields}
    with pytest.raises(ConfigError) as err:
        IndexConfig(**settings)
    assert str(err.value) == message


def test_a_lite_file_in_a_missing_folder(tmp_path: Path) -> None:
    uri = tmp_path / "nowhere" / "maps.db"
    with pytest.raises(MapError) as err:
        PlaceMap(DIM, SHAPE, "fp", index=IndexConfig(kind="milvus", milvus_uri=str(uri)))
    assert str(err.value) == (
        f"cannot open milvus-lite file {uri}: its folder {uri.parent} does not exist; create it "
        "or set milvus_uri to a path in an existing folder"
    )
    assert not uri.parent.exists()


def test_a_lite_path_that_is_a_plain_file(tmp_path: Path) -> None:
    """milvus-lite keeps a "file" in a folder: a plain file there is refused, not overwritten."""
    uri = tmp_path / "maps.db"
    uri.write_text("notes")
    with pytest.raises(MapError) as err:
        PlaceMap(DIM, SHAPE, "fp", index=IndexConfig(kind="milvus", milvus_uri=str(uri)))
    assert str(err.value) == (
        f"cannot open milvus-lite file {uri}: it is a plain file, but milvus-lite keeps its data "
        "in a folder of that name; set milvus_uri to the path the maps were made with or to a "
        "new one"
    )
    assert uri.read_text() == "notes"


def _refused_at_start(uri: str, work_dir: Path) -> str:
    """The MapError text of a map that cannot start on `uri`; it leaves no working folder."""
    with pytest.raises(MapError) as err:
        PlaceMap(DIM, SHAPE, "fp", index=IndexConfig(kind="milvus", milvus_uri=uri),
                 work_dir=work_dir)  # fmt: skip
    assert list(work_dir.iterdir()) == []  # the working folder went with the failed map
    return str(err.value)


def test_a_server_unreachable_at_start(tmp_path: Path) -> None:
    assert _refused_at_start("http://127.0.0.1:9", tmp_path) == (
        "cannot connect to Milvus server http://127.0.0.1:9 (Fail connecting to server on "
        "127.0.0.1:9, illegal connection params or server unavailable): check milvus_uri, that "
        "the server runs and can be reached, and the token in $PAIRVPR_MILVUS_TOKEN"
    )


def test_a_server_of_an_unsupported_version(monkeypatch, tmp_path: Path) -> None:
    """A 2.2 server has no upsert and no count(*): refused at start, before any write."""
    import pymilvus

    class OldServer:
        def __init__(self, *args, **kwargs) -> None:
            pass

        def get_server_version(self) -> str:
            return "v2.2.16"

    monkeypatch.setattr(pymilvus, "MilvusClient", OldServer)
    assert _refused_at_start("http://127.0.0.1:19530", tmp_path) == (
        "Milvus server http://127.0.0.1:19530 runs Milvus v2.2.16, this package needs Milvus 2.3 "
        "or newer (upsert, count(*)): upgrade the server"
    )


def test_a_server_that_refuses_the_token(monkeypatch, tmp_path: Path) -> None:
    """A server that answers (its port accepts connections) but refuses the connection: with
    authorization on, pymilvus says the same as for a server that is gone; the message names
    the token. (test_place_map_milvus_server.py checks it on a real server with authorization.)"""
    import socket

    import pymilvus

    def refuse(*args, **kwargs):
        raise pymilvus.MilvusException(code=2, message="Fail connecting to server")

    monkeypatch.setattr(pymilvus, "MilvusClient", refuse)
    monkeypatch.setenv("PAIRVPR_MILVUS_TOKEN", "root:wrong")
    with socket.create_server(("127.0.0.1", 0)) as server:
        uri = f"http://127.0.0.1:{server.getsockname()[1]}"
        assert _refused_at_start(uri, tmp_path) == (
            f"Milvus server {uri} answers but refused the connection with the token in "
            "$PAIRVPR_MILVUS_TOKEN (Fail connecting to server): a server with authorization "
            "needs a valid 'user:password' or API key in $PAIRVPR_MILVUS_TOKEN; check it (and "
            "that milvus_uri is a Milvus server)"
        )


def test_a_collection_of_another_dimension(milvus) -> None:
    PlaceMap(DIM, SHAPE, "fp", index=milvus).close()
    with pytest.raises(MapError) as err:
        PlaceMap(2 * DIM, SHAPE, "fp", index=milvus)
    assert str(err.value) == (
        f"collection {milvus.milvus_collection!r} in {store_text(milvus)} holds "
        f"8-d descriptors, this map's are 16-d: use another milvus_collection for this model"
    )


def test_a_collection_of_another_model(milvus) -> None:
    PlaceMap(DIM, SHAPE, "model-a", index=milvus).close()
    with pytest.raises(MapFingerprintError) as err:
        PlaceMap(DIM, SHAPE, "model-b", index=milvus)
    assert str(err.value) == (
        f"collection {milvus.milvus_collection!r} in {store_text(milvus)} holds "
        "descriptors of model 'model-a', this map's model is 'model-b': use the same weights and "
        "image size, or another milvus_collection"
    )


def test_a_collection_of_another_program(milvus) -> None:
    from pymilvus import MilvusClient

    client = MilvusClient(milvus.milvus_uri)
    client.create_collection(milvus.milvus_collection, dimension=DIM)  # id + vector, no format
    with pytest.raises(MapError) as err:
        PlaceMap(DIM, SHAPE, "fp", index=milvus)
    assert str(err.value) == (
        f"collection {milvus.milvus_collection!r} in {store_text(milvus)} is not "
        "a pair_vpr_ros keyframe collection (fields ['id', 'vector'], format None; expected "
        "fields ['pk', 'robot', 'session', 'stamp', 'desc']): set milvus_collection to a new "
        "name or to one this package made"
    )


def test_a_server_that_goes_away_is_a_counted_skip(milvus) -> None:
    with PlaceMap(DIM, SHAPE, "fp", index=milvus) as m:
        add_range(m, 0, 4)
        make_flaky(m).down = True
        assert m.add(desc_for(4), dense_for(4), meta_for(4)) == 4  # kept
        with pytest.raises(MapUnavailableError) as err:
            m.search(desc_for(1), 2)
        assert str(err.value) == (
            f"collection {milvus.milvus_collection!r} in {store_text(milvus)} "
            "cannot be reached: query skipped, 1 keyframe(s) kept for insertion"
        )
        assert m.index_diagnostics == {"map_searches_skipped": 1, "map_keyframes_pending": 1}


@pytest.fixture
def saved_milvus(milvus, tmp_path: Path) -> Path:
    with PlaceMap(DIM, SHAPE, "fp", index=milvus) as m:
        add_range(m, 0, 6)
        m.save(tmp_path / "map")
    return tmp_path / "map"


def _set_index(directory: Path, **fields) -> None:
    resign_manifest(directory, lambda data: data["index"].update(fields))


def test_a_saved_map_whose_server_is_gone(saved_milvus: Path) -> None:
    _set_index(saved_milvus, milvus_uri="http://127.0.0.1:9")
    before = tree_digest(saved_milvus)
    with pytest.raises(MapError, match=r"^cannot connect to Milvus server http://127.0.0.1:9 "):
        PlaceMap.load(saved_milvus, "fp")
    assert tree_digest(saved_milvus) == before


def test_a_saved_map_of_another_kind_of_index_file(saved_milvus: Path) -> None:
    _set_index(saved_milvus, kind="hnsw")
    with pytest.raises(MapError) as err:
        PlaceMap.load(saved_milvus, "fp")
    assert str(err.value) == (
        f"{saved_milvus / 'index-1-0.milvus'} is not the index file of a 'hnsw' map: rebuild it"
    )


def test_a_damaged_record(saved_milvus: Path, tmp_path: Path) -> None:
    record = saved_milvus / "index-1-0.milvus"
    with pytest.raises(MapError, match=r"fails its CRC32 check"):  # the store's CRC32 of it
        record.write_bytes(record.read_bytes()[:100])
        PlaceMap.load(saved_milvus, "fp")
    cut = tmp_path / "cut.milvus"
    cut.write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(MapError, match=rf"^milvus record {cut} cannot be read \("):
        read_record(cut, DIM, 6)


def test_a_record_of_another_count(saved_milvus: Path, tmp_path: Path) -> None:
    with pytest.raises(MapError) as err:
        read_record(saved_milvus / "index-1-0.milvus", DIM, 7)
    assert str(err.value) == (
        f"milvus record {saved_milvus / 'index-1-0.milvus'} does not match the manifest (7 "
        f"keyframes of {DIM}-d): the map is damaged, restore it from a backup or rebuild it"
    )


def test_without_pymilvus(monkeypatch, tmp_path) -> None:
    # No store fixture: the map refuses before it connects to anything (a server fixture's
    # clean-up would need the pymilvus this test hides).
    milvus = IndexConfig(kind="milvus", milvus_uri=str(tmp_path / "x.db"))
    monkeypatch.setitem(sys.modules, "pymilvus", None)
    with pytest.raises(ConfigError) as err:
        PlaceMap(DIM, SHAPE, "fp", index=milvus)
    assert str(err.value).startswith(
        "place map index 'milvus' needs the optional packages pymilvus and milvus-lite, which "
        "are not installed ("
    )
    assert str(err.value).endswith(
        "): pip install 'pair_vpr_ros[milvus]' (pymilvus and milvus-lite)"
    )


def test_search_with_an_exclusion_needs_milvus() -> None:
    from pair_vpr_ros.place_map.milvus.expr import Exclusion

    with PlaceMap(DIM, SHAPE, "fp") as m:
        add_range(m, 0, 2)
        with pytest.raises(MapError) as err:
            m.search(desc_for(0), 1, exclusion=Exclusion(0.0, 1.0, 2, "r", "s"))
    assert str(err.value) == "search(exclusion=...) needs index kind 'milvus'; pass allowed="


# ---- issue 38: milvus-lite's own traceback never printed; a user's folder never taken over;
# a read-only open never re-creates a lite file that is gone.
@pytest.mark.parametrize(
    ("uri", "reason"),
    [
        ("/proc/maps.db",
         "FileNotFoundError: [Errno 2] No such file or directory: '/proc/maps.db'"),
        ("/sys/maps.db", "PermissionError: [Errno 1] Operation not permitted: '/sys/maps.db'"),
    ],
)  # fmt: skip
def test_a_lite_file_milvus_lite_cannot_start_on(capfd, uri, reason) -> None:
    """A folder milvus-lite cannot write (as root, /proc and /sys stand in for a read-only
    one): one clear error with milvus-lite's reason, and no traceback of its own."""
    with pytest.raises(MapError) as err:
        PlaceMap(DIM, SHAPE, "fp", index=IndexConfig(kind="milvus", milvus_uri=uri))
    assert str(err.value) == (
        f"cannot open milvus-lite file {uri}: milvus-lite cannot start on it ({reason}); set "
        "milvus_uri to a path in a writable folder"
    )
    out, errs = capfd.readouterr()
    assert "Traceback" not in out + errs and "Failed to start" not in out + errs


def test_a_lite_path_that_is_a_folder_of_other_files(tmp_path: Path) -> None:
    uri = tmp_path / "maps.db"
    uri.mkdir()
    (uri / "notes.txt").write_text("mine")
    with pytest.raises(MapError) as err:
        PlaceMap(DIM, SHAPE, "fp", index=IndexConfig(kind="milvus", milvus_uri=str(uri)))
    assert str(err.value) == (
        f"cannot open milvus-lite file {uri}: it is a folder of other files, not milvus-lite's "
        "data; set milvus_uri to the path the maps were made with or to a new one"
    )
    assert [p.name for p in uri.iterdir()] == ["notes.txt"]


def test_a_read_only_open_of_a_map_whose_lite_file_is_gone(tmp_path: Path) -> None:
    import shutil

    from pair_vpr_ros.place_map.info import map_info

    uri = tmp_path / "own.db"
    config = IndexConfig(kind="milvus", milvus_uri=str(uri), milvus_index="FLAT")
    with PlaceMap(DIM, SHAPE, "fp", index=config) as m:
        add_range(m, 0, 3)
        m.save(tmp_path / "map")
    shutil.rmtree(uri)
    before = tree_digest(tmp_path)
    message = (
        f"cannot open milvus-lite file {uri} of the map in {tmp_path / 'map'} read-only: it is "
        "gone; restore it, or open the map writable to insert its keyframes again"
    )
    with pytest.raises(MapError) as err:
        map_info(tmp_path / "map")
    assert str(err.value).endswith(message)
    assert not uri.exists() and tree_digest(tmp_path) == before


# ---- issue 48: a full disk under a lite file is one error naming it (finding 6); a lite path
# of a saved map that is a plain file is named as damaged, with the way back (finding 7); a
# read-only open never writes the rows the collection lost (loose end 4).
def _full(*_args, **_kwargs):
    import errno

    raise OSError(errno.ENOSPC, "No space left on device")


def test_a_full_disk_under_a_new_lite_file_is_one_error(tmp_path, monkeypatch, capfd) -> None:
    import milvus_lite.db  # the in-process server's storage: where the disk fills up

    monkeypatch.setattr(milvus_lite.db, "save_schema", _full)
    uri = tmp_path / "x.db"
    with pytest.raises(MapError) as err:
        PlaceMap(DIM, SHAPE, "fp", index=IndexConfig(kind="milvus", milvus_uri=str(uri)))
    assert str(err.value) == (
        f"cannot open collection 'pairvpr_keyframes' in milvus-lite file {uri}: its disk is "
        "full ([Errno 28] No space left on device): free disk space there, or set milvus_uri to "
        "a disk with room"
    )
    out, errs = capfd.readouterr()
    assert "Traceback" not in out + errs and "RPC error" not in out + errs


def test_a_full_disk_while_inserting_keeps_the_keyframes(tmp_path, monkeypatch, caplog) -> None:
    from milvus_lite.storage import wal

    uri = tmp_path / "x.db"
    with PlaceMap(DIM, SHAPE, "fp", index=IndexConfig(kind="milvus", milvus_uri=str(uri),
                                                       milvus_index="FLAT")) as m:  # fmt: skip
        add_range(m, 0, 2)
        monkeypatch.setattr(wal.WAL, "write_insert", _full)
        add_range(m, 2, 3)  # kept in the map's copy
        with pytest.raises(MapUnavailableError) as err:
            m.search(desc_for(0), 2)
        assert str(err.value) == (
            f"collection 'pairvpr_keyframes' in milvus-lite file {uri} cannot store rows: its "
            "disk is full ([Errno 28] No space left on device): query skipped, 1 keyframe(s) "
            "kept for insertion"
        )
        assert m.index_diagnostics == {"map_searches_skipped": 1, "map_keyframes_pending": 1}
        monkeypatch.undo()  # room again: the kept keyframe goes in first
        assert m.search(desc_for(2), 1) == [(2, pytest.approx(1.0, abs=1e-5))]
    assert "Traceback" not in caplog.text


def test_a_saved_maps_lite_file_that_is_a_plain_file(tmp_path) -> None:
    import shutil

    uri = tmp_path / "own.db"
    config = IndexConfig(kind="milvus", milvus_uri=str(uri), milvus_index="FLAT")
    with PlaceMap(DIM, SHAPE, "fp", index=config) as m:
        add_range(m, 0, 3)
        m.save(tmp_path / "map")
    shutil.rmtree(uri)
    uri.write_bytes(b"SQLite format 3\0" + bytes(100))  # damaged, or another tool's file
    message = (
        f"cannot open milvus-lite file {uri} of the map in {tmp_path / 'map'}: it is a plain "
        "file, not milvus-lite's data (a folder of that name): damaged or replaced; the map "
        "itself is intact: move the file away and load the map writable once, which inserts "
        "its keyframes again from the map's own copy"
    )
    for read_only in (True, False):
        with pytest.raises(MapError) as err:
            PlaceMap.load(tmp_path / "map", read_only=read_only)
        assert str(err.value) == message
    # (the way back, a writable load inserting the rows into a new lite file, needs a process
    # of its own: milvus-lite keeps serving a file it opened in this one)


def test_a_read_only_open_never_inserts_the_rows_the_collection_lost(tmp_path, caplog) -> None:
    """The collection lost 2 of a map's 4 rows: a read-only open (info, prior maps) inserts
    nothing and answers from the map's own copy, exactly; a writable open inserts them."""
    from pymilvus import MilvusClient

    uri = tmp_path / "own.db"
    config = IndexConfig(kind="milvus", milvus_uri=str(uri), milvus_index="FLAT")
    with PlaceMap(DIM, SHAPE, "fp", index=config) as m:
        add_range(m, 0, 4)
        m.save(tmp_path / "map")
        base = m._index.base
    client = MilvusClient(str(uri))
    client.delete(config.milvus_collection, filter=f"pk >= {base + 2} and pk < {base + 4}")
    client.close()
    with PlaceMap.load(tmp_path / "map", read_only=True) as m:
        assert [m.search(desc_for(i), 1)[0][0] for i in range(4)] == [0, 1, 2, 3]
        assert m._index._count(f"pk >= {base} and pk < {base + 4}") == 2  # nothing written
    assert "held 2 of this map's 4 keyframes; searching the map's own copy of them" in caplog.text
    with PlaceMap.load(tmp_path / "map") as m:
        assert m._index._count(f"pk >= {base} and pk < {base + 4}") == 4
