"""Shared test set-up: keep DDS discovery on this machine before anything can start rclpy, and
keep the user's weights out of the tests."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
# Test runs of several checkouts on one machine must not hear each other: with two /vpr_node
# processes on one domain, both answer every service call. One domain per pytest run (1..100).
os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
os.environ.setdefault("MPLBACKEND", "Agg")
# Weights resolution (pair_vpr_ros.weights) reads PAIRVPR_WEIGHTS and the per-user data folder: a
# checkpoint of the person running the tests must not change what they see (also in the node
# processes the tests start). This folder never exists.
os.environ.pop("PAIRVPR_WEIGHTS", None)
os.environ["XDG_DATA_HOME"] = str(Path(__file__).resolve().parent / "no-user-data")


@pytest.fixture(scope="session")
def tiny_model():
    """The tiny random-init network (seed 0) that core, ros, offline and learn tests run.
    Shared by the whole session: use it read-only (train or modify a model of your own)."""
    from pair_vpr_ros.model import ModelConfig, build_pairvpr  # torch: only when a test needs it

    return build_pairvpr(ModelConfig.tiny(), seed=0)
