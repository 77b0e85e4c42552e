"""Seeded fuzzing of the decoders that read other programs' bytes (issue 38): the fleet wire
decoder (and a robot's exchange behind it) and the loop / factor decoders, over random and
mutated messages. No exception escapes; every message is decoded, refused with a reason, or
counted. A seeded generator stands in for hypothesis (not in the shared venv): the same cases
every run, a few hundred per test, well under 10 s in all."""

from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from loop_records import posed_record

from pair_vpr_ros.errors import FleetMessageError, PoseGraphError
from pair_vpr_ros.fleet import (
    FleetConfig,
    FleetExchange,
    KeyframeDescriptor,
    ScoreRequest,
    ScoreResponse,
    decode,
    encode,
)
from pair_vpr_ros.fleet.wire import Writer
from pair_vpr_ros.identity import Identity, name_problem
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.messages import factor as lf
from pair_vpr_ros.messages.loop import record_dict
from pair_vpr_ros.offline.report.loop_io import read_loops
from pair_vpr_ros.posegraph.loops import loop_problem

S = "20261125T160000Z"
REASONS = {"bad features", "bad name", "corrupt", "duplicate", "malformed", "non-finite",
           "not for this robot", "not normalised", "own robot", "scoring failed", "stale keyframe",
           "stale session", "too large", "unknown keyframe", "unknown robot", "wrong channel",
           "wrong model", "wrong size", "wrong version", "unknown request", "late"}  # fmt: skip
NAME_CHARS = "abcXYZ019_.-/@ é"  # good and bad characters of robot / session ids
FRAME_CHARS = "cam_@/.xyz01"


def text(rng, chars: str, low: int, high: int) -> str:
    return "".join(rng.choice(list(chars), int(rng.integers(low, high + 1))))


def name(rng) -> str:
    """A valid robot id most of the time, else anything (empty, '..', '@', 65 chars, ...)."""
    if rng.random() < 0.7:
        return "r" + text(rng, "abc019_", 0, 10)
    return [text(rng, NAME_CHARS, 0, 6), "..", ".", "x" * 65, "a@b"][int(rng.integers(5))]


def resign(data: bytes) -> bytes:
    return data[:-4] + struct.pack("<I", zlib.crc32(data[:-4]))


def message(rng, tag: bytes) -> bytes:
    """One fleet message of a random kind and content, written without `encode`'s checks."""
    kind = b"DQR"[int(rng.integers(3)) : int(rng.integers(3)) + 1] or b"D"
    w = Writer(kind, tag if rng.random() < 0.8 else bytes(8), name(rng), name(rng))
    stamp = [1.0, math.nan, math.inf, 1e300][int(rng.integers(4))]
    if kind == b"D":
        desc = rng.normal(size=int(rng.choice([512, 512, 8, 0])))
        desc /= max(np.linalg.norm(desc), 1e-9)
        w.pack("IdH", int(rng.integers(0, 5)), stamp, len(desc))
        w.array(desc, "<f2")
    elif kind == b"Q":
        n = int(rng.integers(0, 4))
        w.pack("I", int(rng.integers(0, 9)))
        w.text("a" if rng.random() < 0.7 else name(rng))
        w.text(S)
        w.pack("IdB", 0, stamp, n)
        w.array(rng.integers(0, 3, n), "<u4")
        w.array(rng.random(n), "<f4")
        tokens, width = int(rng.integers(0, 5)), int(rng.integers(0, 9))
        w.pack("IH", tokens, width)
        w.array(rng.normal(size=(tokens, width)), "<f2")
        feats = bytes(rng.integers(0, 256, int(rng.integers(0, 40)), dtype=np.uint8))
        w.pack("I", len(feats))
        w.parts.append(feats)
    else:
        w.pack("I", int(rng.integers(0, 4)))
        w.text("a" if rng.random() < 0.7 else name(rng))
        w.text(S)
        w.pack("IIdfBB", 0, 0, stamp, 1.0, 1, int(rng.integers(0, 2)))
        w.text(text(rng, "metric-", 0, 8))
    return w.finish()


def mutate(rng, data: bytes) -> bytes:
    """`data` as it may arrive: intact, bytes changed, cut, extended, or noise (re-signed or
    not, so both the checksum and the checks behind it are reached)."""
    pick, raw = int(rng.integers(7)), bytearray(data)
    if pick == 1 and raw:
        for _ in range(int(rng.integers(1, 4))):
            raw[int(rng.integers(len(raw)))] = int(rng.integers(256))
    elif pick == 2:
        raw = raw[: int(rng.integers(0, len(raw) + 1))]
    elif pick == 3:
        raw += bytes(rng.integers(0, 256, int(rng.integers(1, 9)), dtype=np.uint8))
    elif pick == 4:
        raw = bytearray(rng.integers(0, 256, int(rng.integers(0, 80)), dtype=np.uint8))
    out = bytes(raw)
    return resign(out) if len(out) >= 4 and rng.random() < 0.6 else out


def test_the_wire_decoder_decodes_or_refuses_with_a_reason():
    rng = np.random.default_rng(38)
    outcomes = {"decoded": 0, "refused": 0}
    for _ in range(600):
        data = mutate(rng, message(rng, b"t" * 8))
        try:
            msg = decode(data)
        except FleetMessageError as err:
            assert err.reason in REASONS, err
            outcomes["refused"] += 1
            continue
        assert isinstance(msg, KeyframeDescriptor | ScoreRequest | ScoreResponse)
        assert name_problem("robot", msg.robot) is None  # every id decoded is usable
        assert name_problem("session", msg.session) is None
        assert decode(encode(msg)) is not None  # and can be sent on as it is
        outcomes["decoded"] += 1
    assert min(outcomes.values()) > 30, outcomes  # both sides of the decoder were reached


def test_an_exchange_counts_every_message(tiny_model):
    rng = np.random.default_rng(7)
    pipe = LoopClosurePipeline(tiny_model, identity=Identity("a", S))
    ex = FleetExchange(pipe, FleetConfig("a", S), lambda out: None, lambda: 0.0, 0)
    ex._pending.update({0: 0.0, 1: 0.0})
    c = ex.counts
    for i in range(300):
        channel = ["keyframes", "request", "response"][i % 3]
        before = (sum(c.skipped.values()), c.ignored, len(ex.store), ex.pending)
        ex.receive(channel, mutate(rng, message(rng, ex.tag)))  # never raises
        after = (sum(c.skipped.values()), c.ignored, len(ex.store), ex.pending)
        used = after[2] > before[2] or after[3] < before[3]
        assert after[0] == before[0] + 1 or after[1] == before[1] + 1 or used, i
    assert sum(c.received.values()) == 300 and set(c.skipped) <= REASONS


def random_factor_msg(rng) -> SimpleNamespace:
    """A nav_msgs/Odometry-like message with random (often damaged) content."""

    def num():
        return [0.5, -1.0, math.nan, math.inf, 1e300, 0.0][int(rng.integers(6))]

    ns = SimpleNamespace
    status = [1.0, 2.0, 3.0, 0.0, math.nan][int(rng.integers(5))]
    return ns(
        header=ns(stamp=ns(sec=int(rng.integers(0, 9)), nanosec=int(rng.integers(0, 9))),
                  frame_id=text(rng, FRAME_CHARS + "r1s", 0, 12)),
        child_frame_id=text(rng, FRAME_CHARS + "r1s", 0, 12),
        pose=ns(pose=ns(position=ns(x=num(), y=num(), z=num()),
                        orientation=ns(x=num(), y=num(), z=num(), w=num())),
                covariance=[num() for _ in range(int(rng.choice([36, 36, 35, 0])))]),
        twist=ns(twist=ns(linear=ns(x=num(), y=0.0, z=status),
                          angular=ns(x=num(), y=2.0, z=3.0))),
    )  # fmt: skip


def test_the_factor_decoder_decodes_or_refuses():
    rng = np.random.default_rng(5)
    for _ in range(400):
        try:
            factor = lf.factor_from_msg(random_factor_msg(rng))
        except ValueError as err:
            assert str(err).startswith("not a loop_closure/factor message: ")
            continue
        for robot, session in ((factor.query_robot, factor.query_session),
                               (factor.match_robot, factor.match_session)):  # fmt: skip
            assert (robot, session) == ("", "") or not (
                name_problem("robot", robot) or name_problem("session", session)
            )
        problem = loop_problem(factor)  # the pose graph's check: a reason or None, no raise
        assert problem is None or isinstance(problem, str)


def test_any_frame_id_and_identity_round_trip_through_the_factor():
    rng = np.random.default_rng(11)
    types = {n: SimpleNamespace for n in lf.FACTOR_MSG_TYPES}
    base = lf.factor_from_record(posed_record())
    for _ in range(300):
        ids = [("r" + text(rng, "ab1_", 0, 4), text(rng, "s01_", 1, 4)), ("", "")]
        q, m = ids[int(rng.integers(2))], ids[int(rng.integers(2))]
        factor = replace(base, query_frame_id=text(rng, FRAME_CHARS, 0, 10),
                         match_frame_id=text(rng, FRAME_CHARS, 0, 10), query_robot=q[0],
                         query_session=q[1], match_robot=m[0], match_session=m[1])  # fmt: skip
        back = lf.factor_from_msg(lf.factor_msg(factor, types))
        blank = dict.fromkeys(lf.IDENTITY, "")
        assert back == (factor if q != m else replace(factor, **blank))


def test_the_loops_json_reader_counts_or_refuses_every_record(tmp_path):
    rng = np.random.default_rng(3)
    good = record_dict(posed_record())
    junk = [None, "x", -1, 1e400, [], {}, math.nan, True]
    for i in range(150):
        record = dict(good)
        for key in rng.choice(list(good), int(rng.integers(0, 4)), replace=False):
            if rng.random() < 0.3:
                del record[key]
            else:
                record[key] = junk[int(rng.integers(len(junk)))]
        path = tmp_path / f"loops{i}.json"
        path.write_text(json.dumps([record]))
        try:
            source = read_loops(path)
        except PoseGraphError as err:
            assert str(err).startswith(f"loop record 1 of {path} is not a loop record")
            continue
        assert source.accepted == len(source.factors) + sum(source.left_out.values())


@pytest.mark.parametrize("seed", [0, 1])
def test_typed_names_are_held_to_the_rule(seed):
    """A decoded message from any transport passes the same names check (messages.check)."""
    from pair_vpr_ros.fleet.messages import check

    rng = np.random.default_rng(seed)
    for _ in range(200):
        robot = name(rng)
        msg = KeyframeDescriptor(robot, S, b"t" * 8, 0, 1.0, np.zeros(4, np.float16))
        try:
            check(msg)
        except FleetMessageError as err:
            assert err.reason in ("bad name", "malformed")
            assert name_problem("robot", robot) is not None
        else:
            assert name_problem("robot", robot) is None
