"""Bad-input matrix, dense codec p4's basis (the head of `dense-g.p4`): a flipped byte (in the
basis, in an entry it re-coded), a head of zeros (lost), a basis-coded entry
without its basis, a file cut inside the head: each a MapError naming the file, at load, and the
saved map unchanged; a basis written past the saved entries (a crash before the save) is fitted
again; a full disk while writing it loses no keyframe."""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np
import pytest
from bad_input import tree_digest
from test_dense_codec_p4 import BASIS_FROM, P4, SHAPE, _desc, _map, _meta, tokens

from pair_vpr_ros.errors import MapError
from pair_vpr_ros.place_map import PlaceMap, dense_store
from pair_vpr_ros.place_map.dense_codec import head_bytes


def _dense(d: Path) -> Path:
    return next(d.glob("dense-*.p4"))


def _flip(path: Path, at: int) -> None:
    data = bytearray(path.read_bytes())
    data[at] ^= 0x10
    path.write_bytes(bytes(data))


def _zero_head(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[: head_bytes(SHAPE, "p4")] = bytes(head_bytes(SHAPE, "p4"))
    path.write_bytes(bytes(data))


def _cut(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: head_bytes(SHAPE, "p4") // 2])


CASES = {
    # name: (map: fitted at BASIS_FROM / adopted by a merge, damage, message)
    "a flipped byte in the basis's matrix": (
        "fitted", lambda p: _flip(p, 200),
        "the p4 basis at the head of {p} fails its check (magic, size or CRC32): the file is "
        "damaged on disk; restore the map from a backup or rebuild it",
    ),
    "a flipped byte in the basis's magic": (
        "fitted", lambda p: _flip(p, 1),
        "the p4 basis at the head of {p} fails its check (magic, size or CRC32)",
    ),
    "a flipped byte in the CRC32s of the entries re-coded with the basis": (
        "fitted", lambda p: _flip(p, 20 + 4 * 32 + 2 * 32 * 32 + 32 + 1),
        "the p4 basis at the head of {p} fails its check (magic, size or CRC32)",
    ),
    "a flipped byte in an entry re-coded with the basis": (
        "fitted", lambda p: _flip(p, head_bytes(SHAPE, "p4") + 5),
        "dense token file {p} does not match its manifest: keyframe 0 fails its CRC32 check",
    ),
    "a head of zeros": (
        "fitted", _zero_head,
        f"the p4 basis at the head of {{p}} is missing (zeros) but keyframes {BASIS_FROM}.. "
        "need it: the file is damaged; restore the map from a backup or rebuild it",
    ),
    "entries coded from entry 0 without their basis": (
        "adopted", _zero_head,
        "dense token file {p} does not match its manifest: keyframe 0 fails its CRC32 check "
        "when read as [64, 32] p4 tokens (dense_shape edited, or the file damaged or from "
        "another map); nothing was changed: restore the map from a backup or rebuild it",
    ),
    "a file cut inside the basis": (
        "fitted", _cut,
        f"dense token file {{p}} is too short: 0 bytes hold 0 keyframes, the manifest lists "
        f"{BASIS_FROM + 3}; the map is damaged (truncated copy?): restore it from a backup or "
        "rebuild it",
    ),
}  # fmt: skip


def _saved(tmp_path: Path, kind: str) -> Path:
    if kind == "fitted":
        return _map(tmp_path / "m", tokens(1, BASIS_FROM + 3))
    a = _map(tmp_path / "a", tokens(1, BASIS_FROM + 1))
    with PlaceMap.load(a, read_only=True) as ma, PlaceMap(8, SHAPE, "fp", P4) as m:
        m.adopt_dense_basis(ma.dense_basis)  # as a merge or compact does
        for i, t in enumerate(tokens(2, 3)):
            m.add(_desc(i), t, _meta(i))  # a few entries, all coded with a's basis
        m.save(tmp_path / "m")
    return tmp_path / "m"


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("read_only", [False, True])
def test_a_damaged_basis_is_a_map_error_and_nothing_changes(
    tmp_path: Path, case: str, read_only: bool
) -> None:
    kind, damage, message = CASES[case]
    d = _saved(tmp_path, kind)
    path = _dense(d)
    damage(path)
    if case == "a file cut inside the basis":
        message = message.replace("0 bytes", f"{path.stat().st_size:,} bytes".replace(",", ""))
    before = tree_digest(d)
    with pytest.raises(MapError) as err:
        PlaceMap.load(d, read_only=read_only)
    assert message.format(p=path) in str(err.value)
    assert tree_digest(d) == before


def test_an_unsaved_basis_past_the_saved_entries_is_fitted_again(tmp_path: Path) -> None:
    """A crash after the basis was written but before the save that needs it: the saved map
    (BASIS_FROM entries) loads, and the next keyframe fits and writes the basis again."""
    data = tokens(3, BASIS_FROM + 2)
    d = _map(tmp_path / "m", data[:BASIS_FROM])
    with PlaceMap.load(d) as m:
        m.add(np.ones(8, np.float32), data[BASIS_FROM], m.meta(0))  # writes the basis; no save
        fitted = m.dense_basis.enc16.copy()
    _flip(_dense(d), 200)  # a torn head: the saved map does not use it
    with PlaceMap.load(d) as m:
        assert m.dense_basis is None
        m.add(np.ones(8, np.float32), data[BASIS_FROM], m.meta(0))
        np.testing.assert_array_equal(m.dense_basis.enc16, fitted)
        m.save(d)
    with PlaceMap.load(d, verify_dense=True) as m:
        assert len(m) == BASIS_FROM + 1 and m.dense_basis is not None


def test_a_full_disk_while_writing_the_basis_loses_no_keyframe(
    tmp_path: Path, monkeypatch
) -> None:
    """The add that fits the basis fails with a MapError; the map keeps its keyframes and the
    next add fits it again (the float16 tokens of the first ones kept)."""
    data = tokens(4, BASIS_FROM + 2)
    real = dense_store.os.pwrite

    def full(fd, payload, offset):
        if offset == 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, payload, offset)

    with PlaceMap(8, SHAPE, "fp", P4) as m:
        for i in range(BASIS_FROM):
            m.add(_desc(i), data[i], _meta(i))
        with monkeypatch.context() as mp:
            mp.setattr(dense_store.os, "pwrite", full)
            with pytest.raises(MapError) as err:
                m.add(_desc(9), data[BASIS_FROM], _meta(9))
        assert "writing the p4 basis to " in str(err.value)
        assert str(err.value).endswith("failed: No space left on device")
        assert len(m) == BASIS_FROM and m.dense_basis is None
        m.add(_desc(9), data[BASIS_FROM], _meta(9))
        assert len(m.dense_basis.recoded) == BASIS_FROM
