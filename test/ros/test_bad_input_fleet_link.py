"""Bad-input matrix, vpr_node's fleet link (issue 38 #2): an owner whose robot id cannot name
a request topic is a counted skip (FleetMessageError "bad name", counted by the exchange), and
a timer tick that fails is logged and counted instead of vanishing in an unread Future."""

from __future__ import annotations

from concurrent.futures import Future
from types import SimpleNamespace

import pytest
import rclpy
from rclpy.qos import QoSProfile

from pair_vpr_ros.errors import FleetMessageError
from pair_vpr_ros.fleet import FleetCounts, Outgoing
from pair_vpr_ros.ros.fleet import FleetLink


@pytest.fixture
def link():
    """A FleetLink around a real node, without the exchange and the map thread."""
    rclpy.init()
    node = rclpy.create_node("fleet_link_test")
    out = FleetLink.__new__(FleetLink)
    out._node, out._owners, out.typed = node, {}, False
    out._request_topic = "/fleet/score_request"
    out._qos = {"request": QoSProfile(depth=4)}
    out.exchange = SimpleNamespace(counts=FleetCounts())
    yield out
    node.destroy_node()
    rclpy.try_shutdown()


@pytest.mark.parametrize("owner", ["x.y", "1r", "a-b"])
def test_an_owner_id_that_cannot_name_a_topic_is_a_bad_name(link, owner):
    with pytest.raises(FleetMessageError) as err:
        link._send(Outgoing("request", owner, b"\x00"))
    assert err.value.reason == "bad name"
    assert str(err.value).startswith(f"bad name: owner {owner!r}: ")
    assert link._owners == {}
    assert link._send(Outgoing("request", "robot_b", b"\x00")) > 0  # a good owner goes on


def test_a_failed_tick_is_logged_and_counted(link, capfd):
    future: Future = Future()
    future.set_exception(RuntimeError("map thread trouble"))
    link._tick_done(future)
    done: Future = Future()
    done.set_result(0)
    link._tick_done(done)
    assert dict(link.exchange.counts.skipped) == {"tick failed": 1}
    assert "fleet exchange tick failed: map thread trouble" in capfd.readouterr().err
