"""The one file digest: the checkpoint's identity and the map manifest's integrity check."""

from __future__ import annotations

import hashlib

from pair_vpr_ros.hashing import sha256_file


def test_sha256_of_a_file_equals_hashlib_over_its_bytes(tmp_path):
    data = bytes(range(256)) * 40_000  # ~10 MB: several read blocks
    (tmp_path / "f").write_bytes(data)
    (tmp_path / "empty").write_bytes(b"")
    assert sha256_file(tmp_path / "f") == hashlib.sha256(data).hexdigest()
    assert sha256_file(str(tmp_path / "empty")) == hashlib.sha256(b"").hexdigest()
