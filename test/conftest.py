"""Shared test set-up: keep DDS discovery on this machine before anything can start rclpy, and
keep the user's weights out of the tests; fixtures every test can ask for (also when its file
runs alone: fixtures live here, or in a conftest.py beside the tests, never only in another test
module); tests of an optional extra skip where it is not installed (test/extras.py)."""

from __future__ import annotations

import hashlib
import importlib.util
import itertools
import os
from pathlib import Path

import pytest
from extras import in_ci, reason_in
from milvus_fixtures import lite_db, milvus, server_milvus, store  # noqa: F401 - milvus fixtures

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
# Nodes must not hear nodes of another test: with two /vpr_node on one domain, both answer every
# service call and a graph query by node name may describe the other one. A node stopped by an
# earlier test (or another checkout's test run) can linger in discovery for the 20 s participant
# lease when it left without saying goodbye, so every test gets a domain of its own (1..100, a
# different sequence per pytest process) unless the person running the tests chose one.
_USER_DOMAIN = os.environ.get("ROS_DOMAIN_ID")
_DOMAINS = itertools.count(os.getpid() * 37)
os.environ.setdefault("MPLBACKEND", "Agg")
# Weights resolution (pair_vpr_ros.weights) reads PAIRVPR_WEIGHTS and the per-user data folder: a
# checkpoint of the person running the tests must not change what they see (also in the node
# processes the tests start). This folder never exists.
os.environ.pop("PAIRVPR_WEIGHTS", None)
os.environ["XDG_DATA_HOME"] = str(Path(__file__).resolve().parent / "no-user-data")


@pytest.fixture(scope="session", autouse=True)
def _user_cache(tmp_path_factory):
    """The OpenVINO back end keeps converted models in $XDG_CACHE_HOME/pair_vpr_ros/ (the node's
    and the replay's default): the tests' go to a temporary folder, never the user's ~/.cache
    (also in the node processes the tests start, which inherit the environment)."""
    before = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("xdg-cache"))
    yield
    if before is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = before


@pytest.fixture(scope="session", autouse=True)
def _openvino_graphs_once():
    """Exporting and converting a network for OpenVINO takes 10-30 s on 2 cores, and a dozen
    tests start the back end on the same tiny weights: within this process the graphs of one
    set of weights are built once and each start gets its own copy. What the tests check (cache
    entries written and read, int8 calibration, outputs) is unchanged; a test that must see a
    start build nothing patches `openvino_backend.build_graphs` itself, over this memo."""
    if importlib.util.find_spec("openvino") is None:
        yield
        return
    from pair_vpr_ros.model import openvino_backend

    build, built = openvino_backend.build_graphs, {}

    def memo(ov, model, chunk):
        digest = hashlib.sha256(repr(model.config).encode())
        for name, value in model.state_dict().items():
            digest.update(name.encode() + value.detach().cpu().contiguous().numpy().tobytes())
        key = (digest.hexdigest(), chunk)
        if key not in built:
            built[key] = build(ov, model, chunk)
        return {name: graph.clone() for name, graph in built[key].items()}

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(openvino_backend, "build_graphs", memo)
        yield


@pytest.fixture(scope="session")
def tiny_model():
    """The tiny random-init network (seed 0) that core, ros, offline and learn tests run.
    Shared by the whole session: use it read-only (train or modify a model of your own)."""
    from pair_vpr_ros.model import ModelConfig, build_pairvpr  # torch: only when a test needs it

    return build_pairvpr(ModelConfig.tiny(), seed=0)


@pytest.fixture(autouse=True)
def _ros_domain(monkeypatch):
    """A fresh ROS_DOMAIN_ID for each test, set before any fixture can start rclpy (read by
    rclpy.init in this process and by the node processes a test starts)."""
    if _USER_DOMAIN is None:
        monkeypatch.setenv("ROS_DOMAIN_ID", str(1 + next(_DOMAINS) % 100))


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    """A test module that cannot be imported because an extra's module is missing: skipped,
    with the pip command (failed under CI)."""
    outcome = yield
    report = outcome.get_result()
    reason = reason_in(str(report.longrepr)) if report.failed and not in_ci() else None
    if reason:
        report.outcome, report.longrepr = "skipped", (str(collector.path), 0, reason)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A test that fails on an extra's missing module (imported where it is used, also when
    the package wraps it: a ConfigError raised `from` it): skipped."""
    outcome = yield
    report = outcome.get_result()
    error = call.excinfo.value if call.excinfo is not None else None
    seen = set()  # an exception's chain can loop back (A's context B, B's context A)
    while (
        error is not None and not isinstance(error, ModuleNotFoundError) and id(error) not in seen
    ):
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    if not isinstance(error, ModuleNotFoundError):
        error = None
    if report.failed and error is not None and not in_ci():
        reason = reason_in(f"ModuleNotFoundError: No module named '{error.name}'")
        if reason:
            report.outcome = "skipped"
            report.longrepr = (str(item.path), item.location[1] or 0, f"Skipped: {reason}")
