"""Bad-input matrix: typed fleet messages (pair_vpr_ros_interfaces) that cannot be fleet
messages raise FleetMessageError with a countable reason; good ones round-trip exactly."""

from __future__ import annotations

from array import array

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from pair_vpr_ros.errors import ConfigError, FleetMessageError
from pair_vpr_ros.fleet import KeyframeDescriptor, ScoreRequest, ScoreResponse, encode, model_tag
from pair_vpr_ros.fleet.typed import from_typed, to_typed
from pair_vpr_ros.messages.loop import POSE_STATUS_CODES
from pair_vpr_ros.ros import fleet

msgs = pytest.importorskip("pair_vpr_ros_interfaces.msg")
CLASSES = {n: getattr(msgs, n) for n in ("KeyframeDescriptor", "ScoreRequest", "ScoreResponse")}
CODES = POSE_STATUS_CODES
TAG, S = model_tag("m"), "20261125T160000Z"


def descriptor():
    v = np.random.default_rng(0).normal(size=512)
    return KeyframeDescriptor("robot_a", S, TAG, 5, 12.25, (v / np.linalg.norm(v)).astype("f2"))


def request():
    dense = np.random.default_rng(1).normal(size=(16, 32)).astype(np.float16)
    return ScoreRequest("b", S, TAG, 9, "a", S, 3, 7.5, [4, 1], [0.75, 0.5], dense, b"feat")


def response():
    return ScoreResponse("a", S, TAG, 9, "b", S, 3, 4, 2.5, 1.5, 2, True, "metric-odometry")


@pytest.mark.parametrize("make", [descriptor, request, response])
def test_typed_round_trip_is_exact_and_about_the_codec_size(make):
    msg = make()
    typed = to_typed(msg, CLASSES, CODES)
    back = from_typed(typed, CODES)
    for name, value in vars(msg).items():
        got = getattr(back, name)
        assert np.array_equal(got, value) if isinstance(value, np.ndarray) else got == value
    assert abs(len(serialize_message(typed)) - len(encode(msg))) < 64


def test_a_512_d_typed_descriptor_fits_in_1_5_kb():
    assert len(serialize_message(to_typed(descriptor(), CLASSES, CODES))) < 1536


def mutate(make, **fields):
    typed = to_typed(make(), CLASSES, CODES)
    for name, value in fields.items():
        setattr(typed, name, value)
    return typed


CASES = {
    "descriptor of an odd byte count": (
        descriptor,
        dict(descriptor=array("B", b"\0" * 1023)),
        "wrong size",
    ),  # fmt: skip
    "dim not the data's": (descriptor, dict(dim=256), "wrong size"),
    "no candidates": (
        request,
        dict(candidate_ids=array("q"), global_similarities=array("f")),
        "malformed",
    ),  # fmt: skip
    "65 candidates": (request, dict(candidate_ids=array("q", range(65))), "malformed"),
    "tokens not token_count x token_dim": (request, dict(token_count=17), "wrong size"),
}


@pytest.mark.parametrize("case", CASES)
def test_bad_typed_messages_raise_a_countable_reason(case):
    make, fields, reason = CASES[case]
    with pytest.raises(FleetMessageError) as err:
        from_typed(mutate(make, **fields), CODES)
    assert err.value.reason == reason


def test_not_a_fleet_message():
    with pytest.raises(FleetMessageError, match="not a fleet message type: LoopClosure"):
        from_typed(msgs.LoopClosure(), CODES)


UNUSABLE = "UnsupportedTypeSupport: Could not import 'rosidl_typesupport_c' for package 'x'"


def test_fleet_messages_whose_type_support_does_not_load(monkeypatch):
    """The package imports but its C library does not load (a node started by another
    environment): auto falls back to bytes with one warning, typed stops with a clear error."""
    monkeypatch.setattr(fleet, "typed_unusable", lambda classes: UNUSABLE)
    warned: list[str] = []
    assert fleet.typed_wanted("auto", warned.append) is False
    assert warned == [
        f"fleet_messages auto: bytes, because pair_vpr_ros_interfaces cannot be used "
        f"({UNUSABLE}); every robot of the fleet must use the same kind"
    ]
    with pytest.raises(ConfigError) as err:
        fleet.typed_wanted("typed", warned.append)
    assert str(err.value) == (
        f"fleet_messages is typed but pair_vpr_ros_interfaces cannot be used ({UNUSABLE}): "
        "`make setup` builds it and the node must start from its environment "
        "(docs/interfaces.md), or use fleet_messages bytes on every robot"
    )
    assert fleet.typed_wanted("bytes", warned.append) is False and len(warned) == 1
