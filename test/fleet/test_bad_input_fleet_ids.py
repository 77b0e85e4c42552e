"""Bad-input matrix, issue 38: ids that cannot name a folder, a topic or a key, garbage
keypoints in score requests, and a transport that cannot reach an owner. Each is a counted
skip under its reason; nothing kept is lost, nothing raises."""

from __future__ import annotations

import re

import numpy as np
import pytest

from pair_vpr_ros.errors import FleetMessageError
from pair_vpr_ros.fleet import (
    FleetConfig,
    FleetExchange,
    KeyframeDescriptor,
    ScoreRequest,
    ScoreResponse,
    encode,
)
from pair_vpr_ros.fleet.owner import check_features
from pair_vpr_ros.fleet.peers import PeerHit, Proposal
from pair_vpr_ros.fleet.wire import Writer
from pair_vpr_ros.geometry.epipolar import verify_pair
from pair_vpr_ros.geometry.features import Features, pack_features, unpack_features
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline

S = "20261125T160000Z"
BAD_IDS = ["x.y", ".", "..", "a/b", "a@b", "1r", "fleet_summary.json", "a b", "é"]


@pytest.fixture
def owner(tiny_model):
    """Robot "a" (geometric verification on) with two keyframes; what it sent is in `sent`."""
    config = DetectorConfig(score_threshold=-1e6, keyframe_max_similarity=0.99999,
                            geometric_verification=True, min_inliers=8)  # fmt: skip
    geometry = GeometryConfig(relative_pose=False)
    pipe = LoopClosurePipeline(tiny_model, config, geometry=geometry, identity=Identity("a", S))
    sent = []
    ex = FleetExchange(pipe, FleetConfig("a", S), sent.append, lambda: 0.0, 0)
    rng = np.random.default_rng(0)
    for t in range(2):
        ex.on_keyframe(pipe.process(Frame(float(t), rng.integers(0, 256, (48, 64, 3), np.uint8))))
    sent.clear()
    return ex, sent


def unit(dim=512, seed=1):
    v = np.random.default_rng(seed).normal(size=dim)
    return (v / np.linalg.norm(v)).astype(np.float16)


def raw_descriptor(ex, robot: str, session: str = S) -> bytes:
    """A descriptor with any robot / session on the wire (`encode` refuses bad names)."""
    w = Writer(b"D", ex.tag, robot, session)
    desc = unit()
    w.pack("IdH", 0, 1.0, len(desc))
    w.array(desc, "<f2")
    return w.finish()


@pytest.mark.parametrize("robot", BAD_IDS)
def test_a_peer_id_that_breaks_the_identity_rule_is_counted(owner, robot):
    ex, sent = owner
    ex.receive("keyframes", raw_descriptor(ex, "b"))  # kept before the bad one
    ex.receive("keyframes", raw_descriptor(ex, robot))
    ex.receive("keyframes", raw_descriptor(ex, "c", session=robot))
    session_ok = robot == "1r"  # a session may start with a digit (its default is a time)
    assert dict(ex.counts.skipped) == {"bad name": 1 if session_ok else 2}
    assert [r[0] for r in ex.store.rows] == ["b", "c"][: 2 if session_ok else 1]
    assert sent == []


def test_bad_names_of_typed_messages_are_counted(owner):
    ex, _ = owner
    msgs = [
        ("keyframes", KeyframeDescriptor("x.y", S, ex.tag, 0, 1.0, unit())),
        ("request", ScoreRequest("b", S, ex.tag, 1, "a", "..", 0, 1.0, [0], [0.9],
                                 np.zeros((4, 8), np.float16))),
        ("response", ScoreResponse("b", S, ex.tag, 1, "a@b", S, 0, 0, 1.0, 1.0, 1, True)),
    ]  # fmt: skip
    for channel, msg in msgs:
        assert ex.handle(channel, msg, 100) is None
    assert dict(ex.counts.skipped) == {"bad name": 3}


@pytest.mark.parametrize("robot", ["x.y", ".."])
def test_bad_names_cannot_be_encoded(owner, robot):
    ex, _ = owner
    with pytest.raises(FleetMessageError) as err:
        encode(KeyframeDescriptor(robot, S, ex.tag, 0, 1.0, unit()))
    assert str(err.value) == (
        f"bad name: robot {robot!r} must be 1-64 characters of ASCII letters, digits or '_' (a "
        "robot id starts with a letter): it names folders, a ROS topic and pose-graph keys, "
        "e.g. robot1"
    )


def features(keypoints: np.ndarray) -> bytes:
    n = len(keypoints)
    desc = np.random.default_rng(3).integers(0, 256, (n, 128)).astype(np.uint8)
    # version 1: garbage keypoints arrive as sent (a compact record cannot hold NaN or inf)
    return pack_features(Features(np.asarray(keypoints, np.float32), desc), compact=False)


def request(ex, feats: bytes) -> ScoreRequest:
    n, d = ex.pipe.model.num_patches, ex.pipe.model.config.embed_dim
    return ScoreRequest("b", S, ex.tag, 5, "a", S, 0, 9.0, [1, 0], [0.9, 0.8],
                        np.zeros((n, d), np.float16), feats)  # fmt: skip


GARBAGE = {
    "NaN keypoints": (np.full((40, 2), np.nan), "keypoints are not finite [M, 2] pixels"),
    "inf keypoints": (np.full((40, 2), np.inf), "keypoints are not finite [M, 2] pixels"),
    "1e30 keypoints": (np.full((40, 2), 1e30), "keypoints beyond 1e+05 px"),
    "identical keypoints": (np.full((40, 2), 7.0), "most keypoints repeat one position"),
}


@pytest.mark.parametrize("case", GARBAGE)
def test_a_request_with_garbage_keypoints_is_counted_not_scored(owner, case):
    ex, sent = owner
    keypoints, detail = GARBAGE[case]
    with pytest.raises(FleetMessageError, match=f"^bad features: {re.escape(detail)}$"):
        check_features(unpack_features(features(keypoints)))
    assert ex.receive("request", encode(request(ex, features(keypoints)))) is None
    assert dict(ex.counts.skipped) == {"bad features": 1}
    assert sent == [] and ex.counts.loops_accepted == ex.counts.loops_rejected == 0


def test_verification_never_reuses_an_earlier_mask():
    """cv2.findFundamentalMat gives no F for degenerate points; the inliers must be 0, not
    the mask of the call before."""
    rng = np.random.default_rng(1)
    desc = rng.integers(0, 256, (60, 128)).astype(np.uint8)
    pts = rng.uniform(0, 600, (60, 2)).astype(np.float32)
    good = verify_pair(Features(pts, desc), Features(pts + 3.0, desc))
    assert good[0] >= 8  # a pure shift: every match fits one F
    for bad in (np.full((60, 2), 5.0), np.full((60, 2), 1e30), np.full((60, 2), np.nan)):
        kp = np.asarray(bad, np.float32)
        assert verify_pair(Features(kp, desc), Features(kp.copy(), desc)) == (0, 0.0)


def test_a_transport_that_cannot_reach_an_owner_is_counted(owner):
    """A request the transport refuses (e.g. no topic for that owner) is a counted skip."""
    ex, _ = owner

    def refuse(out):
        if out.channel == "request":
            raise FleetMessageError("bad name", f"owner {out.target!r}")

    ex.send = refuse
    ex.receive("keyframes", encode(KeyframeDescriptor("b", S, ex.tag, 0, 1.0, unit())))
    hit = PeerHit("b", S, 0, 1.0, 0.9)
    assert ex._ask(Proposal(0.9, 0, ex.pipe.place_map.meta(0).stamp, ("b", S), [hit])) == 0
    assert dict(ex.counts.skipped) == {"bad name": 1} and ex.pending == 0
