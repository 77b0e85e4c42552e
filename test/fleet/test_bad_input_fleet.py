"""Bad-input matrix: fleet messages (issue 22 part 4). Every message a robot cannot use is
counted under its reason and skipped; nothing raises, nothing already kept is lost."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from pair_vpr_ros.errors import ConfigError, FleetMessageError
from pair_vpr_ros.fleet import (
    FleetConfig,
    FleetExchange,
    KeyframeDescriptor,
    ScoreRequest,
    ScoreResponse,
    encode,
    model_tag,
)
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline

S = "20261125T160000Z"


@pytest.fixture
def owner(tiny_model):
    """Robot "a" with two keyframes in its map; what it sent is kept in `sent`."""
    config = DetectorConfig(score_threshold=-1e6, keyframe_max_similarity=0.99999)
    pipe = LoopClosurePipeline(tiny_model, config, identity=Identity("a", S))
    sent = []
    ex = FleetExchange(pipe, FleetConfig("a", S, peers=("b", "c")), sent.append, lambda: 0.0, 0)
    rng = np.random.default_rng(0)
    for t in range(2):
        ex.on_keyframe(pipe.process(Frame(float(t), rng.integers(0, 256, (48, 64, 3), np.uint8))))
    sent.clear()
    return ex, sent


def unit(dim=512, seed=1):
    v = np.random.default_rng(seed).normal(size=dim)
    return (v / np.linalg.norm(v)).astype(np.float16)


def descriptor(ex, **kw):
    fields = dict(robot="b", session=S, model=ex.tag, keyframe_id=0, stamp=1.0, descriptor=unit())
    return KeyframeDescriptor(**{**fields, **kw})


def resign(data: bytes) -> bytes:
    """`data` with its checksum recomputed (a well-formed message with wrong content)."""
    return data[:-4] + struct.pack("<I", zlib.crc32(data[:-4]))


def request(ex, **kw):
    n, d = ex.pipe.model.num_patches, ex.pipe.model.config.embed_dim
    fields = dict(robot="b", session=S, model=ex.tag, request_id=5, owner_robot="a",
                  owner_session=S, query_id=0, query_stamp=9.0, candidate_ids=[1, 0],
                  similarities=[0.9, 0.8], dense=np.zeros((n, d), np.float16))  # fmt: skip
    return ScoreRequest(**{**fields, **kw})


def nan_desc():
    v = unit()
    v[3] = np.nan
    return v


GOOD = encode(KeyframeDescriptor("b", S, model_tag("x"), 0, 1.0, unit()))
DESCRIPTOR_CASES = {
    "empty": (lambda ex: b"", "malformed"),
    "random bytes": (lambda ex: bytes(range(200)), "malformed"),
    "truncated": (lambda ex: encode(descriptor(ex))[:-10], "corrupt"),
    "one byte changed": (
        lambda ex: encode(descriptor(ex))[:50] + b"\0" + encode(descriptor(ex))[51:],
        "corrupt",
    ),  # fmt: skip
    "trailing bytes": (
        lambda ex: resign(encode(descriptor(ex))[:-4] + b"xx" + b"cccc"),
        "wrong size",
    ),  # fmt: skip
    "ends early": (lambda ex: resign(encode(descriptor(ex))[:-100] + b"cccc"), "malformed"),
    "wrong version": (lambda ex: resign(GOOD[:4] + b"\x07" + GOOD[5:]), "wrong version"),
    "unknown kind": (lambda ex: resign(GOOD[:3] + b"Z" + GOOD[4:]), "malformed"),
    "wrong model": (lambda ex: encode(descriptor(ex, model=model_tag("other"))), "wrong model"),
    "wrong size (256-d)": (lambda ex: encode(descriptor(ex, descriptor=unit(256))), "wrong size"),
    "NaN": (lambda ex: encode(descriptor(ex, descriptor=nan_desc())), "non-finite"),
    "inf stamp": (lambda ex: encode(descriptor(ex, stamp=float("inf"))), "non-finite"),
    "not normalised": (
        lambda ex: encode(descriptor(ex, descriptor=unit() * 3)),
        "not normalised",
    ),  # fmt: skip
    "unknown robot": (lambda ex: encode(descriptor(ex, robot="z")), "unknown robot"),
    "own robot, other session": (
        lambda ex: encode(descriptor(ex, robot="a", session="old")),
        "own robot",
    ),  # fmt: skip
    "on the request channel": (lambda ex: encode(descriptor(ex)), "wrong channel"),
}


@pytest.mark.parametrize("case", DESCRIPTOR_CASES)
def test_bad_descriptors_are_counted_and_skipped(owner, case):
    ex, sent = owner
    ex.receive("keyframes", encode(descriptor(ex, keyframe_id=7)))  # kept before the bad one
    make, reason = DESCRIPTOR_CASES[case]
    channel = "request" if case == "on the request channel" else "keyframes"
    assert ex.receive(channel, make(ex)) is None
    assert dict(ex.counts.skipped) == {reason: 1}
    assert len(ex.store) == 1 and ex.store.rows[0][2] == 7  # nothing kept was lost
    assert sent == []


def test_duplicate_and_reordered_descriptors(owner):
    ex, _ = owner
    for kf_id in (3, 1, 3, 2):
        msg = descriptor(ex, keyframe_id=kf_id, descriptor=unit(seed=kf_id))
        ex.receive("keyframes", encode(msg))
    assert dict(ex.counts.skipped) == {"duplicate": 1}
    assert [r[2] for r in ex.store.rows] == [3, 1, 2]  # late ones kept, counted as reordered
    assert (ex.store.reordered, ex.store.missing()) == (2, 1)  # id 0 never heard


def test_own_descriptors_heard_back_are_ignored(owner):
    ex, _ = owner
    ex.receive("keyframes", encode(descriptor(ex, robot="a", keyframe_id=1)))
    assert (ex.counts.ignored, len(ex.store), dict(ex.counts.skipped)) == (1, 0, {})


REQUEST_CASES = {
    "dense of another model size": (dict(dense=np.zeros((4, 8), np.float16)), "wrong size"),
    "keyframe the owner lacks": (dict(candidate_ids=[1, 9]), "unknown keyframe"),
    "candidate twice": (dict(candidate_ids=[1, 1]), "unknown keyframe"),
    "owner's old session": (dict(owner_session="19700101T000000Z"), "stale session"),
    "for another robot": (dict(owner_robot="c"), "not for this robot"),
    "from this robot's id": (dict(robot="a"), "own robot"),
    "wrong model": (dict(model=model_tag("other")), "wrong model"),
    "NaN similarity": (dict(similarities=[float("nan"), 0.8]), "non-finite"),
}


@pytest.mark.parametrize("case", REQUEST_CASES)
def test_bad_requests_are_counted_and_not_scored(owner, case):
    ex, sent = owner
    changes, reason = REQUEST_CASES[case]
    assert ex.receive("request", encode(request(ex, **changes))) is None
    assert dict(ex.counts.skipped) == {reason: 1}
    assert sent == [] and ex.counts.loops_accepted == ex.counts.loops_rejected == 0


def test_a_request_is_scored_once_however_often_it_arrives(owner):
    ex, sent = owner
    data = encode(request(ex))
    loop = ex.receive("request", data)
    assert loop is not None and loop.record.accepted and loop.record.match_id in (0, 1)
    assert ex.receive("request", data) is None
    assert dict(ex.counts.skipped) == {"duplicate": 1}
    assert [o.channel for o in sent] == ["response"]


def test_requests_with_zero_or_too_many_candidates_cannot_be_encoded(owner):
    ex, _ = owner
    for ids in ([], list(range(65))):
        with pytest.raises(FleetMessageError, match="^too large: "):
            encode(request(ex, candidate_ids=ids, similarities=[0.5] * len(ids)))
    data = bytearray(encode(request(ex)))
    count_at = 3 + 1 + 1 + 8 + 2 + 17 + 4 + 2 + 17 + 4 + 8  # the candidate count byte
    data[count_at] = 0
    assert ex.receive("request", resign(bytes(data))) is None
    assert dict(ex.counts.skipped) == {"malformed": 1}


def response(ex, **kw):
    fields = dict(robot="b", session=S, model=ex.tag, request_id=0, requester_robot="a",
                  requester_session=S, query_id=0, match_id=0, match_stamp=1.0, pair_score=1.0,
                  scored=1, accepted=True)  # fmt: skip
    return ScoreResponse(**{**fields, **kw})


def test_bad_responses_are_counted(owner):
    ex, _ = owner
    ex._pending[0] = 0.0  # one request of ours is waiting
    ex.receive("response", encode(response(ex, request_id=44)))
    ex.receive("response", encode(response(ex, requester_session="old")))
    ex.receive("response", encode(response(ex, requester_robot="c")))  # another robot's
    ex.receive("response", encode(response(ex)))
    ex.receive("response", encode(response(ex)))
    assert dict(ex.counts.skipped) == {"unknown request": 1, "stale session": 1, "duplicate": 1}
    assert (ex.counts.ignored, ex.counts.loops_confirmed, ex.pending) == (1, 1, 0)


def test_a_late_response_is_counted_late(owner):
    ex, _ = owner
    ex._pending[3] = 0.0
    ex.clock = lambda: 100.0
    assert ex.expire() == 1
    ex.receive("response", encode(response(ex, request_id=3)))
    assert (dict(ex.counts.skipped), ex.counts.timeouts, ex.counts.loops_confirmed) == (
        {"late": 1},
        1,
        0,
    )


@pytest.mark.parametrize(
    "changes, message",
    [
        (
            dict(robot=""),
            "fleet robot '' must be 1-64 characters of ASCII letters, digits or "
            "'_' (a robot id starts with a letter): it names folders, a ROS topic and pose-graph "
            "keys, e.g. robot1",
        ),
        (dict(robot=".."), "fleet robot '..' must be 1-64 characters"),
        (dict(robot="x.y"), "fleet robot 'x.y' must be 1-64 characters"),
        (dict(session="s" * 65), "fleet session 'sss"),
        (dict(peers=("b", "../c")), "fleet_peers robot '../c' must be 1-64 characters"),
        (dict(budget=-1), "fleet budget=-1 is out of range"),
        (dict(top_k=0), "fleet top_k=0 is out of range"),
        (dict(period_s=float("nan")), "fleet period_s=nan is out of range"),
        (dict(timeout_s=0.0), "fleet timeout_s=0.0 is out of range"),
        (dict(peer_search="kafka"), "fleet peer_search='kafka' is out of range"),
        (
            dict(peers=("a", "b")),
            "fleet_peers ['a', 'b'] name this robot 'a': list the other "
            "robots it listens to ('' = any robot)",
        ),
    ],
)
def test_bad_fleet_config_is_a_clear_error(changes, message):
    with pytest.raises(ConfigError) as err:
        FleetConfig(**{"robot": "a", "session": S, **changes})
    assert str(err.value).startswith(message)


def test_requests_for_keyframes_of_a_cleared_map_are_refused(owner):
    ex, sent = owner
    ex.pipe.clear_map()  # ids 0 and 1 were published; the map now holds another keyframe 0
    rng = np.random.default_rng(9)
    ex.pipe.process(Frame(50.0, rng.integers(0, 256, (48, 64, 3), np.uint8)))
    for ids in ([0], [1]):
        data = encode(request(ex, candidate_ids=ids, similarities=[0.9]))
        assert ex.receive("request", data) is None
    assert dict(ex.counts.skipped) == {"stale keyframe": 2} and sent == []
