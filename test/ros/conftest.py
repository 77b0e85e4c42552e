"""Fixtures of the node tests: `harness(**parameters)` makes a `node_harness.Harness` inside an
rclpy context and closes it afterwards; `typed_messages` is pair_vpr_ros_interfaces.msg."""

from __future__ import annotations

import os

import pytest
import rclpy
from node_harness import Harness


@pytest.fixture
def harness():
    """A factory of harnesses; all are closed, and rclpy shut down, after the test."""
    rclpy.init()
    made: list[Harness] = []

    def make(**kwargs) -> Harness:
        made.append(Harness(**kwargs))
        return made[-1]

    yield make
    for h in made:
        h.close()
    rclpy.try_shutdown()


@pytest.fixture(scope="session")
def typed_messages():
    """The module `pair_vpr_ros_interfaces.msg` (built into the venv by `make setup`). Its tests
    are skipped where it is not built (PAIRVPR_INTERFACES=skip) and fail in CI, where the
    set-up must have built it."""
    try:
        import pair_vpr_ros_interfaces.msg as msg
    except ImportError as err:
        text = f"pair_vpr_ros_interfaces is not built ({err}): `make setup` builds it"
        if os.environ.get("CI"):
            pytest.fail(text)
        pytest.skip(text)
    return msg
