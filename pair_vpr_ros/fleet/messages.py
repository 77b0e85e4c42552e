"""The three fleet messages and their byte encodings (the contract between robots; the ROS
topics carry these bytes). Layout of the common header: `wire.py`.

    descriptor (D):   keyframe id u32, stamp f64, dim u16, descriptor float16 [dim]
    score request (Q): request id u32, owner robot, owner session, query keyframe id u32,
                       query stamp f64, n u8, candidate ids u32 [n], similarities f32 [n],
                       tokens u32 (N), width u16 (D), dense float16 [N, D],
                       features u32 length + the query's packed keyframe features (may be empty)
    score response (R): request id u32, requester robot, requester session, query id u32,
                       match id u32, match stamp f64, pair score f32, scored u8, accepted u8,
                       pose status

`decode` checks what one message can show on its own (layout, checksum, finite numbers);
what needs state (own robot, model, expected sizes, duplicates) is checked by the receiver.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pair_vpr_ros.errors import FleetMessageError
from pair_vpr_ros.fleet.wire import TAG_BYTES, Reader, Writer, check_name

MAX_CANDIDATES = 64
MAX_TOKENS = 1 << 14
MAX_WIDTH = 4096
MAX_FEATURES_BYTES = 1 << 24


@dataclass
class KeyframeDescriptor:
    """One keyframe of one robot: global descriptor float16 [dim]."""

    robot: str
    session: str
    model: bytes  # wire.model_tag of the fingerprint
    keyframe_id: int
    stamp: float
    descriptor: np.ndarray


@dataclass
class ScoreRequest:
    """Ask `owner_robot` to pair-score its keyframes `candidate_ids` against the requester's
    query keyframe, whose dense tokens [N, D] float16 travel with the request."""

    robot: str  # the requester
    session: str
    model: bytes
    request_id: int
    owner_robot: str
    owner_session: str
    query_id: int
    query_stamp: float
    candidate_ids: list[int]
    similarities: list[float]
    dense: np.ndarray
    features: bytes = b""


@dataclass
class ScoreResponse:
    """The owner's decision on one request: its best candidate and whether it was accepted."""

    robot: str  # the owner
    session: str
    model: bytes
    request_id: int
    requester_robot: str
    requester_session: str
    query_id: int
    match_id: int
    match_stamp: float
    pair_score: float
    scored: int
    accepted: bool
    pose_status: str = field(default="")


Message = KeyframeDescriptor | ScoreRequest | ScoreResponse


def encode(msg: Message) -> bytes:
    """A message -> its bytes; FleetMessageError("bad name" / "too large") for what the
    layout cannot hold."""
    check_name("robot", msg.robot)
    check_name("session", msg.session)
    if isinstance(msg, KeyframeDescriptor):
        w = Writer(b"D", msg.model, msg.robot, msg.session)
        desc = np.asarray(msg.descriptor).reshape(-1)
        w.pack("IdH", msg.keyframe_id, msg.stamp, len(desc))
        w.array(desc, "<f2")
        return w.finish()
    if isinstance(msg, ScoreRequest):
        return _encode_request(msg)
    w = Writer(b"R", msg.model, msg.robot, msg.session)
    w.pack("I", msg.request_id)
    w.text(check_name("requester robot", msg.requester_robot))
    w.text(check_name("requester session", msg.requester_session))
    w.pack("IIdfBB", msg.query_id, msg.match_id, msg.match_stamp, msg.pair_score, msg.scored,
           msg.accepted)  # fmt: skip
    w.text(msg.pose_status)
    return w.finish()


def _encode_request(msg: ScoreRequest) -> bytes:
    n, dense = len(msg.candidate_ids), np.asarray(msg.dense)
    if not 1 <= n <= MAX_CANDIDATES or len(msg.similarities) != n:
        raise FleetMessageError("too large", f"{n} candidates (1..{MAX_CANDIDATES})")
    if dense.ndim != 2 or dense.shape[0] > MAX_TOKENS or dense.shape[1] > MAX_WIDTH:
        raise FleetMessageError("too large", f"dense tokens of shape {list(dense.shape)}")
    if len(msg.features) > MAX_FEATURES_BYTES:
        raise FleetMessageError("too large", f"{len(msg.features)} bytes of features")
    w = Writer(b"Q", msg.model, msg.robot, msg.session)
    w.pack("I", msg.request_id)
    w.text(check_name("owner robot", msg.owner_robot))
    w.text(check_name("owner session", msg.owner_session))
    w.pack("IdB", msg.query_id, msg.query_stamp, n)
    w.array(np.asarray(msg.candidate_ids), "<u4")
    w.array(np.asarray(msg.similarities), "<f4")
    w.pack("IH", *dense.shape)
    w.array(dense, "<f2")
    w.pack("I", len(msg.features))
    w.parts.append(bytes(msg.features))
    return w.finish()


def decode(data: bytes | bytearray | memoryview) -> Message:
    """Bytes -> the message they hold; FleetMessageError with a countable `reason` otherwise."""
    r = Reader(data)
    if r.kind == b"D":
        kf_id, stamp, dim = r.unpack("IdH")
        desc = r.array(dim, "<f2")
        r.end()
        return check(KeyframeDescriptor(r.robot, r.session, r.tag, kf_id, stamp, desc))
    if r.kind == b"Q":
        return _decode_request(r)
    request_id = r.unpack("I")[0]
    requester, requester_session = r.text(), r.text()
    query_id, match_id, match_stamp, score, scored, accepted = r.unpack("IIdfBB")
    status = r.text()
    r.end()
    return check(ScoreResponse(r.robot, r.session, r.tag, request_id, requester,
                               requester_session, query_id, match_id, match_stamp, float(score),
                               scored, bool(accepted), status))  # fmt: skip


def _decode_request(r: Reader) -> ScoreRequest:
    request_id = r.unpack("I")[0]
    owner, owner_session = r.text(), r.text()
    query_id, query_stamp, n = r.unpack("IdB")
    if not 1 <= n <= MAX_CANDIDATES:
        raise FleetMessageError("malformed", f"{n} candidates")
    ids, sims = r.array(n, "<u4"), r.array(n, "<f4")
    tokens, width = r.unpack("IH")
    if tokens > MAX_TOKENS or width > MAX_WIDTH:
        raise FleetMessageError("malformed", f"dense tokens of shape [{tokens}, {width}]")
    dense = r.array(tokens * width, "<f2").reshape(tokens, width)
    features = r.take(r.unpack("I")[0])
    r.end()
    return check(ScoreRequest(r.robot, r.session, r.tag, request_id, owner, owner_session,
                              query_id, query_stamp, ids.astype(int).tolist(),
                              sims.astype(float).tolist(), dense, features))  # fmt: skip


def check(msg: Message) -> Message:
    """What one message can show on its own, however it arrived (codec bytes or a typed ROS
    message): names present, a model tag of 8 bytes, request sizes, finite numbers."""
    if not msg.robot or not msg.session or len(msg.model) != TAG_BYTES:
        raise FleetMessageError("malformed", "empty robot or session id, or no model tag")
    if isinstance(msg, KeyframeDescriptor):
        _finite("descriptor", msg.stamp, msg.descriptor)
    elif isinstance(msg, ScoreRequest):
        n = len(msg.candidate_ids)
        if not 1 <= n <= MAX_CANDIDATES or len(msg.similarities) != n:
            raise FleetMessageError("malformed", f"{n} candidates, {len(msg.similarities)} sims")
        if not msg.owner_robot or not msg.owner_session or np.ndim(msg.dense) != 2:
            raise FleetMessageError("malformed", "no owner, or dense tokens not [N, D]")
        _finite("request", msg.query_stamp, np.asarray(msg.similarities), msg.dense)
    else:
        _finite("response", msg.match_stamp, np.float32(msg.pair_score))
    for what, name in _names(msg):  # ids that cannot name a topic, a folder or a key
        check_name(what, name)
    return msg


def _names(msg: Message) -> list[tuple[str, str]]:
    out = [("robot", msg.robot), ("session", msg.session)]
    if isinstance(msg, ScoreRequest):
        out += [("owner robot", msg.owner_robot), ("owner session", msg.owner_session)]
    elif isinstance(msg, ScoreResponse):
        out += [("requester robot", msg.requester_robot),
                ("requester session", msg.requester_session)]  # fmt: skip
    return out


def _finite(what: str, stamp: float, *arrays: np.ndarray) -> None:
    if not math.isfinite(stamp) or not all(np.isfinite(a).all() for a in arrays):
        raise FleetMessageError("non-finite", f"{what} holds NaN or inf")
