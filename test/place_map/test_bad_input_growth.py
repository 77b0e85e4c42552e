"""Bad-input matrix, the growth tables and `pairvpr-map compact` (issue 34 part 3): every bad
input is one `error:` line and a non-zero exit, the input map unchanged, no OUT left behind; a
damaged growth row is reported when read, never used."""

from __future__ import annotations

import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from bad_input import tree_digest
from map_fixtures import make_map

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.offline.map_cli import main
from pair_vpr_ros.place_map import PlaceMap

MAPS = Path(__file__).resolve().parents[1] / "data" / "maps"


def _with_growth(path: Path) -> Path:
    """A saved map of 3 keyframes with signatures and a link (keyframe 2 to 0)."""
    make_map(path, "r1", "mon", 3, seed=1)
    with PlaceMap.load(path) as m:
        for i in range(3):
            m.growth.add_signature(i, np.full(96, 0.1 * i, np.float32))
        m.growth.add_link(2, 0, (0.5, 0, 0, 0, 0, 0, 1))
        m.save(path)
    return path


def _damage(path: Path, sql: str) -> None:
    conn = sqlite3.connect(path / "map-1.sqlite")
    conn.execute(sql)
    conn.commit()
    conn.close()


CASES = {
    # name: (IN builder, extra args, exit code, error text)
    "OUT exists": (
        lambda t: (t / "out").mkdir() or _with_growth(t / "a"), [], 1,
        "--out {t}/out exists: compact never writes into an existing folder; give a new one",
    ),
    "IN missing": (
        lambda t: t / "none", [], 1, "input map {t}/none does not exist or is not a folder",
    ),
    "IN not a map": (
        lambda t: (t / "empty").mkdir() or t / "empty", [], 1,
        "input map {t}/empty cannot be compacted: {t}/empty/manifest.json is missing",
    ),
    "IN corrupt": (
        lambda t: _with_growth(t / "a").joinpath("map-1.sqlite").write_bytes(b"x") and t / "a",
        [], 1,
        "input map {t}/a cannot be compacted: keyframe store {t}/a/map-1.sqlite cannot be read "
        "(no such table: keyframes)",
    ),
    "IN of another model": (
        lambda t: _with_growth(t / "a"), ["--fingerprint", "model-b"], 1,
        "input map {t}/a holds model 'model-a', not 'model-b': compact maps of that model only, "
        "or leave out --fingerprint",
    ),
    "IN of an old format": (
        lambda t: Path(shutil.copytree(MAPS / "format-2", t / "old")), [], 1,
        "input map {t}/old is of format version 2: compact reads formats 3-4; load it in the node "
        "or a replay (--map-dir) and save it once to convert it, then compact",
    ),
    "a damaged signature": (
        lambda t: _damage(_with_growth(t / "a"), "UPDATE signatures SET crc = crc + 1 WHERE "
                          "id = 1") or t / "a", [], 1,
        "keyframe store {t}/a/map-1.sqlite holds the signature of keyframe 1 with a wrong CRC32 "
        "(a damaged row): the map is damaged; restore it from a backup or rebuild it",
    ),
    "a damaged link": (
        lambda t: _damage(_with_growth(t / "a"), "UPDATE links SET tx = 9.0") or t / "a", [], 1,
        "keyframe store {t}/a/map-1.sqlite holds the link of keyframes 2 and 0 with a wrong "
        "CRC32 (a damaged row)",
    ),
    "a damaged link score": (  # issue 48: a link's CRC32 covers its re-rank score
        lambda t: _damage(_with_growth(t / "a"), "UPDATE links SET score = 5.0") or t / "a", [],
        1, "keyframe store {t}/a/map-1.sqlite holds the link of keyframes 2 and 0 with a wrong "
        "CRC32 (a damaged row)",
    ),
    "a store of a newer schema": (
        lambda t: _damage(_with_growth(t / "a"), "PRAGMA user_version = 9") or t / "a", [], 1,
        "input map {t}/a cannot be compacted: keyframe store {t}/a/map-1.sqlite has schema "
        "version 9, this pair_vpr_ros reads up to 1: it was written by a newer pair_vpr_ros; use "
        "that release",
    ),
    "a bad codec": (lambda t: _with_growth(t / "a"), ["--codec", "q2"], 2, ""),
}  # fmt: skip


@pytest.mark.parametrize("case", list(CASES))
def test_bad_compact_is_an_error_line_and_leaves_nothing(tmp_path, capsys, case):
    build, extra, code, message = CASES[case]
    src = build(tmp_path)
    before = tree_digest(tmp_path)
    out = tmp_path / "out"
    existed = out.exists()
    assert main(["compact", str(src), "--out", str(out), *extra]) == code
    err = capsys.readouterr().err
    if code == 1:
        assert err.startswith("error: ") and err.count("\n") == 1
        assert message.format(t=tmp_path) in err
    else:
        assert "invalid choice: 'q2'" in err
    assert tree_digest(tmp_path) == before and out.exists() == existed
    assert not [p for p in tmp_path.iterdir() if ".merging-" in p.name]


def test_growth_rows_of_a_read_only_map_are_refused(tmp_path):
    with PlaceMap.load(_with_growth(tmp_path / "a"), read_only=True) as m:
        assert m.growth.counts().signatures == 3
        with pytest.raises(MapError, match="cannot record growth rows in a map loaded with "
                           "read_only=True"):  # fmt: skip
            m.growth.add_signature(0, np.zeros(96))


def test_growth_rows_added_after_the_last_save_are_rolled_back_like_keyframes(tmp_path):
    path = _with_growth(tmp_path / "a")
    with PlaceMap.load(path) as m:
        m.growth.add_link(1, 0, (0, 0, 0, 0, 0, 0, 1))  # never saved
    with PlaceMap.load(path, read_only=True) as m:
        assert m.growth.counts().links == 1


def test_a_full_disk_while_recording_a_growth_row_is_a_map_error(tmp_path):
    with PlaceMap.load(_with_growth(tmp_path / "a")) as m:
        tables = m.growth
        real = tables._conn

        class Full:  # the store's connection, whose writes find the disk full
            def execute(self, sql, *args):
                if sql.startswith("INSERT"):
                    raise sqlite3.OperationalError("database or disk is full")
                return real.execute(sql, *args)

        tables._conn = Full()
        with pytest.raises(MapError) as err:
            tables.add_link(1, 0, (0, 0, 0, 0, 0, 0, 1))
        assert str(err.value) == (
            f"keyframe store {tmp_path / 'a' / 'map-1.sqlite'} could not record a growth row: the "
            "disk is full (database or disk is full): free disk space there (SQLite also writes "
            "temporary files to $TMPDIR) and retry"
        )
