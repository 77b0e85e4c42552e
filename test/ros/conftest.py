"""Fixtures of the node tests: `harness(**parameters)` makes a `node_harness.Harness` inside an
rclpy context and closes it afterwards."""

from __future__ import annotations

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
