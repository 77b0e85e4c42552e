"""The byte layout shared by every fleet message (little-endian, see docs/fleet-exchange.md).

    magic "PVF" | kind (1 byte: D descriptor, Q score request, R score response) | version u8
    | model tag (8 bytes: sha256 of the model fingerprint) | sender robot | sender session
    | body (per kind) | crc32 u32 of everything before it

Strings are a u8 length and that many UTF-8 bytes. Reading never trusts a length: a message
that ends early, has trailing bytes or fails its checksum raises `FleetMessageError` with a
short `reason`, which receivers count (they never crash on a message).
"""

from __future__ import annotations

import hashlib
import struct
import zlib

import numpy as np

from pair_vpr_ros.errors import FleetMessageError
from pair_vpr_ros.identity import name_problem

MAGIC = b"PVF"
VERSION = 1
KINDS = {b"D": "descriptor", b"Q": "score request", b"R": "score response"}
TAG_BYTES = 8
MAX_NAME = 64  # robot and session ids: at most this many bytes (identity.py's rule)


def model_tag(fingerprint: str) -> bytes:
    """8 bytes naming a model: robots whose tags differ never mix descriptors or tokens."""
    return hashlib.sha256(fingerprint.encode("utf-8")).digest()[:TAG_BYTES]


def check_name(what: str, name: str) -> str:
    """A robot or session id fit for the wire and for every output: the identity rule
    (identity.py; `what` names a robot or a session); FleetMessageError("bad name") if not."""
    problem = name_problem(what, name)
    if problem:
        raise FleetMessageError("bad name", problem)
    return name


class Writer:
    """Builds one message: header first, then body fields, then `finish()` adds the crc."""

    def __init__(self, kind: bytes, tag: bytes, robot: str, session: str) -> None:
        self.parts = [MAGIC, kind, bytes([VERSION]), tag]
        self.text(robot)
        self.text(session)

    def pack(self, fmt: str, *values) -> None:
        self.parts.append(struct.pack("<" + fmt, *values))

    def text(self, value: str) -> None:
        data = value.encode("utf-8")
        self.parts += [bytes([len(data)]), data]

    def array(self, values: np.ndarray, dtype: str) -> None:
        self.parts.append(np.ascontiguousarray(values, dtype).tobytes())

    def finish(self) -> bytes:
        data = b"".join(self.parts)
        return data + struct.pack("<I", zlib.crc32(data))


class Reader:
    """Reads one message; every problem is a `FleetMessageError` ("malformed", "corrupt", ...)."""

    def __init__(self, data: bytes | bytearray | memoryview) -> None:
        data = bytes(data)
        if len(data) < 4 + 3 + TAG_BYTES + 2 + 4 or data[:3] != MAGIC:
            raise FleetMessageError("malformed", "not a fleet message (too short or no magic)")
        body, crc = data[:-4], struct.unpack("<I", data[-4:])[0]
        if zlib.crc32(body) != crc:
            raise FleetMessageError("corrupt", "checksum mismatch")
        self.data, self.pos = body, 3
        self.kind = self.take(1)
        if self.kind not in KINDS:
            raise FleetMessageError("malformed", f"unknown message kind {self.kind!r}")
        version = self.take(1)[0]
        if version != VERSION:
            raise FleetMessageError("wrong version", f"version {version}, this reads {VERSION}")
        self.tag = self.take(TAG_BYTES)
        self.robot = self.text()
        self.session = self.text()

    @property
    def size(self) -> int:
        return len(self.data) + 4

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise FleetMessageError("malformed", "message ends early")
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str) -> tuple:
        fmt = "<" + fmt
        return struct.unpack(fmt, self.take(struct.calcsize(fmt)))

    def text(self) -> str:
        raw = self.take(self.take(1)[0])
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as err:
            raise FleetMessageError("malformed", "a name is not UTF-8") from err

    def array(self, count: int, dtype: str) -> np.ndarray:
        size = np.dtype(dtype).itemsize
        return np.frombuffer(self.take(count * size), dtype).copy()

    def end(self) -> None:
        if self.pos != len(self.data):
            raise FleetMessageError("wrong size", f"{len(self.data) - self.pos} bytes left over")
