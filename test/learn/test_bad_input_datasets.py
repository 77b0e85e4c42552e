"""Bad-input matrix, datasets: ground-truth .npy files are never unpickled (issue 13 #4: an
object array used to run code) and give a DatasetError for any other content; CSV lists that are
not UTF-8 or not CSV give a DatasetError naming the file (they used to end in a traceback)."""

from __future__ import annotations

import csv
import io
import os
import re
from pathlib import Path

import numpy as np
import pytest
from synthetic_data import place_image, write_rgb
from test_datasets import README_ROW, _gsv_city

from pair_vpr_ros.errors import DatasetError
from pair_vpr_ros.learn.eval_sets import GT_CONVERT, load_eval_set
from pair_vpr_ros.learn.places import load_gldv2, load_gsv_cities

DB, QUERIES = 3, 2


class Exploit:
    """Unpickling this runs `touch <marker>`."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture
def eval_root(tmp_path: Path) -> Path:
    for folder, count in (("database", DB), ("queries", QUERIES)):
        for i in range(count):
            write_rgb(tmp_path / folder / f"{i:03d}.png", place_image(i, 0, 16))
    return tmp_path


def _save(array) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=True)
    return buffer.getvalue()


def _ragged() -> np.ndarray:
    gt = np.empty(QUERIES, dtype=object)
    gt[0], gt[1] = np.array([2, 0]), np.array([], dtype=np.int64)
    return gt


def _exploit(root: Path) -> np.ndarray:
    gt = np.empty(QUERIES, dtype=object)
    gt[0], gt[1] = Exploit(root / "pwned"), np.array([0])
    return gt


GT_CASES = {
    "ragged object array": (lambda r: _save(_ragged()), "is an object array (a ragged list"),
    "pickle exploit": (lambda r: _save(_exploit(r)), "a pickle can run code: it is not loaded"),
    "empty file": (lambda r: b"", "is not a NumPy .npy file (it starts with b'')"),
    "random bytes": (lambda r: bytes(range(256)) * 4, "is not a NumPy .npy file"),
    "plain pickle": (lambda r: b"\x80\x04K\x01.", "is not a NumPy .npy file"),
    "npz archive": (lambda r: b"PK\x03\x04" + bytes(60), "is not a NumPy .npy file"),
    "truncated npy": (lambda r: _save(np.zeros((QUERIES, 4), np.int64))[:100], "cannot read"),
    "header only": (lambda r: _save(np.zeros((QUERIES, 4), np.int64))[:10], "cannot read"),
    "float indices": (
        lambda r: _save(np.array([[0.0], [1.0]])),
        "holds a float64 array of shape [2, 1]; expected an integer [queries, K] array",
    ),
    "3-d array": (lambda r: _save(np.zeros((QUERIES, 1, 1), np.int64)), "of shape [2, 1, 1]"),
    "scalar": (lambda r: _save(np.int64(3)), "has a scalar but there are 2 queries"),
    "too few queries": (lambda r: _save(np.array([[0]])), "has 1 entries but there are 2"),
    "index past the database": (
        lambda r: _save(np.array([[0], [DB]])),
        f"query 1 names database index outside 0..{DB - 1}",
    ),
    "negative index": (lambda r: _save(np.array([[0], [-2]])), "query 1 names database index"),
    "bool of the wrong width": (
        lambda r: _save(np.ones((QUERIES, DB + 1), bool)),
        "holds a bool array of shape [2, 4]",
    ),
}


@pytest.mark.parametrize("case", list(GT_CASES))
def test_bad_ground_truth(eval_root: Path, case: str) -> None:
    make, message = GT_CASES[case]
    (eval_root / "ground_truth.npy").write_bytes(make(eval_root))
    with pytest.raises(DatasetError, match=re.escape(message)) as info:
        load_eval_set(eval_root)
    assert str(eval_root / "ground_truth.npy") in str(info.value)
    assert not (eval_root / "pwned").exists()  # nothing was unpickled


def test_the_conversion_command_makes_a_loadable_file(eval_root: Path) -> None:
    """The one-liner the object-array error gives turns the ragged file into the padded one."""
    import subprocess
    import sys

    (eval_root / "ground_truth.npy").write_bytes(_save(_ragged()))
    command = GT_CONVERT.replace("python -c ", "", 1).strip('"').replace('\\"', '"')
    subprocess.run([sys.executable, "-c", command], cwd=eval_root, check=True)
    assert [p.tolist() for p in load_eval_set(eval_root).positives] == [[0, 2], []]


# ---- CSV lists

NON_UTF8 = "it is not UTF-8 text (byte b'\\xe9': invalid continuation byte); save it as UTF-8"


def _gsv_bytes(root: Path, data: bytes) -> None:
    _gsv_city(root, "London", [README_ROW], with_images=1)
    (root / "Dataframes" / "London.csv").write_bytes(data)


def _header() -> bytes:
    return (",".join(README_ROW) + "\n").encode()


CSV_CASES = {
    "latin-1 city": (
        lambda r: _gsv_bytes(r, _header() + "130,2018,4,15,Montr\xe9al,1,2,x\n".encode("latin-1")),
        NON_UTF8,
    ),
    "binary": (lambda r: _gsv_bytes(r, b"\xff\xfe\x00\x01" * 20), "it is not UTF-8 text"),
    "huge field": (
        lambda r: _gsv_bytes(r, _header() + b'"' + b"x" * (csv.field_size_limit() + 10) + b'"\n'),
        "field larger than field limit",
    ),
    "malformed row": (
        lambda r: _gsv_bytes(r, _header() + b"one,2018,4,15,London,1,2,x\n"),
        "London.csv:2: malformed row",
    ),
}


@pytest.mark.parametrize("case", list(CSV_CASES))
def test_bad_gsv_dataframe(tmp_path: Path, case: str) -> None:
    make, message = CSV_CASES[case]
    make(tmp_path)
    with pytest.raises(DatasetError, match=re.escape(message)) as info:
        load_gsv_cities(tmp_path)
    assert "London.csv" in str(info.value)


def test_gldv2_list_that_is_not_utf8(tmp_path: Path) -> None:
    (tmp_path / "train").mkdir()
    (tmp_path / "train.csv").write_bytes(b"id,url,landmark_id\nabc,http://caf\xe9,5\n")
    with pytest.raises(DatasetError, match=re.escape(NON_UTF8)):
        load_gldv2(tmp_path)
