"""The fleet codec: exact round trips and exact sizes (the wire contract between robots)."""

from __future__ import annotations

import numpy as np
import pytest

from pair_vpr_ros.errors import FleetMessageError
from pair_vpr_ros.fleet import (
    KeyframeDescriptor,
    ScoreRequest,
    ScoreResponse,
    decode,
    encode,
    model_tag,
)
from pair_vpr_ros.fleet.wire import TAG_BYTES

TAG = model_tag("random-init:0|tiny|56px|desc512|dense32")
SESSION = "20261125T160000Z"
HEADER = 3 + 1 + 1 + TAG_BYTES + 4  # magic, kind, version, model tag, crc32


def test_model_tag_is_8_bytes_of_sha256():
    assert model_tag("x").hex() == "2d711642b726b044"
    assert model_tag("x") != model_tag("y") and len(TAG) == TAG_BYTES


def test_a_512_d_descriptor_round_trips_in_1080_bytes():
    desc = np.random.default_rng(0).normal(size=512).astype(np.float16)
    msg = KeyframeDescriptor("robot_a", SESSION, TAG, 41, 1234.5678, desc)
    data = encode(msg)
    # header + names (1 + 7, 1 + 16) + id, stamp, dim (4 + 8 + 2) + 512 float16
    assert len(data) == HEADER + 8 + 17 + 14 + 1024 == 1080
    back = decode(data)
    assert (back.robot, back.session, back.model, back.keyframe_id, back.stamp) == (
        "robot_a", SESSION, TAG, 41, 1234.5678,
    )  # fmt: skip
    assert back.descriptor.dtype == np.float16 and np.array_equal(back.descriptor, desc)


def test_the_largest_names_still_fit_in_1_5_kb():
    msg = KeyframeDescriptor("r" * 64, "s" * 64, TAG, 0, 0.0, np.zeros(512, np.float16))
    assert len(encode(msg)) == HEADER + 65 + 65 + 14 + 1024 == 1185


def test_a_vit_b_request_carries_the_query_tokens_once():
    dense = np.random.default_rng(1).normal(size=(529, 768)).astype(np.float16)
    msg = ScoreRequest("b", SESSION, TAG, 7, "a", SESSION, 3, 12.5, [4, 9, 2], [0.9, 0.8, 0.7],
                       dense, b"feat")  # fmt: skip
    data = encode(msg)
    fixed = HEADER + 2 + 17 + 4 + 2 + 17 + 4 + 8 + 1 + 3 * 8 + 4 + 2 + 4
    assert len(data) == fixed + 529 * 768 * 2 + 4 == 812_654  # "feat": 4 bytes
    back = decode(data)
    assert (back.request_id, back.owner_robot, back.candidate_ids, back.features) == (
        7, "a", [4, 9, 2], b"feat",
    )  # fmt: skip
    assert np.allclose(back.similarities, [0.9, 0.8, 0.7]) and np.array_equal(back.dense, dense)


def test_a_response_is_small():
    msg = ScoreResponse("a", SESSION, TAG, 7, "b", SESSION, 3, 9, 4.25, 1.5, 3, True, "metric")
    data = encode(msg)
    assert len(data) == HEADER + 2 + 17 + 4 + 2 + 17 + 4 + 4 + 8 + 4 + 1 + 1 + 7 == 88
    assert decode(data) == msg


@pytest.mark.parametrize(
    "msg, reason",
    [
        (KeyframeDescriptor("", SESSION, TAG, 0, 0.0, np.zeros(4)), "bad name"),
        (KeyframeDescriptor("a", "é" * 33, TAG, 0, 0.0, np.zeros(4)), "bad name"),
        (
            ScoreRequest("a", "s", TAG, 0, "b", "s", 0, 0.0, [1], [0.5], np.zeros((3, 4, 5))),
            "too large",
        ),  # fmt: skip
        (
            ScoreRequest("a", "s", TAG, 0, "b", "s", 0, 0.0, [1], [0.5, 0.4], np.zeros((3, 4))),
            "too large",
        ),  # fmt: skip
    ],
)
def test_what_the_layout_cannot_hold_is_refused_when_encoding(msg, reason):
    with pytest.raises(FleetMessageError) as err:
        encode(msg)
    assert err.value.reason == reason
