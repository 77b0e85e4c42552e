"""`vpr_node` under what a robot does every day (issue 17): a bag played again or a clock reset
(stamps going back), and `loop_closure` remapped for LIO-SAM (every output follows it). In one
process: the node and a peer publishing and listening (`node_harness`)."""

from __future__ import annotations

import json

import cv2
import pytest
import rclpy
from bag_fixtures import synthetic_images
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from node_harness import diagnostics, wait_for
from std_srvs.srv import Trigger

from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.ros.outputs import publish_while_up


@pytest.fixture(scope="module")
def places():
    return synthetic_images(6, size=32)


def test_stamps_going_back_never_publish_a_pair_with_t_current_not_after_t_previous(
    harness, places
):
    h = harness()
    everything = [places[i] for i in range(6)]
    h.publish(everything, t0=100.0)
    h.publish(everything, t0=100.0)  # the bag played again: the same images at the same stamps
    h.publish(everything[:2], t0=50.0)  # a clock reset to before the first pass
    h.publish(everything[2:4], t0=200.0)  # time moves on: revisits of the first pass
    h.processed(16)
    wait_for(
        lambda: (
            diagnostics(h).get("loops") == "2"
            and diagnostics(h).get("loops_unordered") == "2"
            and diagnostics(h).get("clock_jumps") == "2"
        )
    )
    pairs = [list(m.data) for m in h.got["loop_closure"]]
    assert all(current > previous for current, previous in pairs), pairs
    assert pairs == [[200.0, 102.0], [201.0, 103.0]]
    # the loops after the reset (into the first pass's "future") are on detail and json only
    wait_for(lambda: len(h.got["loop_closure/json"]) == 4)
    records = [json.loads(m.data) for m in h.got["loop_closure/json"]]
    assert [(r["query_stamp"], r["match_stamp"]) for r in records] == [
        (50.0, 100.0), (51.0, 101.0), (200.0, 102.0), (201.0, 103.0)
    ]  # fmt: skip
    assert h.node.stats.counts.errors == 0


def test_every_output_follows_a_remapped_loop_closure(harness, places):
    base = "/lio_loop/loop_closure_detection"
    h = harness(remap=base)
    h.publish([places[i] for i in (0, 1, 2, 0)], t0=100.0)
    h.processed(4)
    wait_for(lambda: len(h.got["loop_closure"]) == 1 and len(h.got["loop_closure/json"]) == 1)
    assert list(h.got["loop_closure"][0].data) == [103.0, 100.0]
    assert len(h.got["loop_closure/detail"]) == 1
    subs = ["detail", "json", "factor", "markers", "image"]
    subs += ["typed"] if h.node.outputs.typed else []
    expected = {base, *(f"{base}/{s}" for s in subs)}

    def published() -> dict[str, list[str]]:
        return dict(h.peer.get_publisher_names_and_types_by_node("vpr_node", "/"))

    wait_for(lambda: expected <= set(published()))  # the graph is discovered, not instant
    assert {t for t in published() if "loop" in t} == expected
    assert published()[base] == ["std_msgs/msg/Float64MultiArray"]
    if h.node.outputs.typed:  # pair_vpr_ros_interfaces is built (test_typed_loop_closure.py)
        assert published()[f"{base}/typed"] == ["pair_vpr_ros_interfaces/msg/LoopClosure"]


def diagnostic_level(h) -> bytes | None:
    """Level of the newest /diagnostics status (None before the first message)."""
    return h.got["/diagnostics"][-1].status[0].level if h.got["/diagnostics"] else None


def test_build_map_reports_to_a_script_and_a_failure_is_an_error_until_a_success(
    harness, tmp_path
):
    # Issue 17 #5: a build into a file answered success and failed later; a failed build left
    # /diagnostics at OK. map_info is what a script polls after build_map.
    a_file = tmp_path / "map.txt"
    a_file.write_text("x")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "a.png").write_bytes(b"not a png")
    good = tmp_path / "good"
    good.mkdir()
    for i, rgb in enumerate(synthetic_images(2, size=32)):
        (good / f"{i}.png").write_bytes(cv2.imencode(".png", rgb)[1].tobytes())
    h = harness(map_dir=str(a_file), build_source=str(good))

    def info() -> dict:
        return json.loads(h.call(Trigger, "map_info").message)

    reply = h.call(Trigger, "build_map")
    assert not reply.success and reply.message.startswith(f"map_dir {a_file} is a file")
    assert info()["build"]["state"] == "idle"
    h.set(map_dir=str(tmp_path / "map"), build_source=str(broken))
    assert h.call(Trigger, "build_map").success
    wait_for(lambda: info()["build"]["state"] == "failed")
    wait_for(lambda: diagnostic_level(h) == DiagnosticStatus.ERROR)
    assert (
        h.got["/diagnostics"][-1]
        .status[0]
        .message.startswith(f"building a map from {broken} into ")
    )
    h.set(build_source=str(good))
    assert h.call(Trigger, "build_map").success
    wait_for(lambda: info()["build"]["state"] == "done")
    assert info()["keyframes"] == 2 and info()["build"]["error"] == ""
    wait_for(lambda: diagnostic_level(h) == DiagnosticStatus.OK)


def test_save_on_shutdown_without_map_dir_warns_at_start_up(harness, capfd):
    # Issue 17 #7: it saved nothing and said nothing.
    harness(save_on_shutdown=True)
    wait_for(lambda: "save_on_shutdown is true but map_dir is empty" in capfd.readouterr().err)


def test_nothing_is_published_once_the_context_is_shut_down(harness, places):
    # Issue 17 #4: a stop signal shuts the context down at once; a timer callback publishing
    # then raised "Failed to publish: publisher's context is invalid" (exception never retrieved).
    h = harness()
    h.publish([places[i] for i in (0, 1, 2, 0)], t0=100.0)
    h.processed(4)
    wait_for(lambda: len(h.got["loop_closure"]) == 1)
    rclpy.shutdown()
    assert not publish_while_up(h.node, h.node.pub_diag, DiagnosticArray())
    h.node._publish_diagnostics()  # the timer's callback: no exception
    outcome, loops = h.node.maps.process(Frame(104.0, places[1], "cam"))
    [(loop, match_pose)] = loops
    h.node._publish_loop(loop, None, match_pose)  # the worker's
    assert outcome.loop.accepted and h.node.stats.counts.loops == 2
