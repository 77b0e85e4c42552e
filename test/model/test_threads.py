"""model.threads: one CPU thread count for the process, `auto` by the model's size."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.model import ModelConfig
from pair_vpr_ros.model.threads import (
    auto_threads,
    check_threads,
    encode_gmac,
    resolve_threads,
    usable_cores,
)


def test_encode_work_of_the_demo_model_and_vitb():
    # linear layers only: depth x (patches + class + 4 registers) x (4 D^2 + 2 D x hidden)
    assert encode_gmac(ModelConfig.preset("small")) == pytest.approx(4 * 69 * 196_608 / 1e9)
    assert encode_gmac(ModelConfig.preset("B")) == pytest.approx(12 * 534 * 7_077_888 / 1e9)
    assert encode_gmac(ModelConfig.preset("B")) == pytest.approx(45.35, abs=0.01)


def test_auto_is_one_thread_for_light_networks_and_every_core_for_vitb():
    for light in ("tiny", "small"):
        assert auto_threads(ModelConfig.preset(light), cores=8) == 1
    for size in ("S", "B", "L", "G"):
        assert auto_threads(ModelConfig.preset(size), cores=8) == 8
    assert auto_threads(ModelConfig.preset("B")) == usable_cores()
    assert resolve_threads(0, ModelConfig.preset("small")) == 1
    assert resolve_threads(3, ModelConfig.preset("small")) == 3


@pytest.mark.parametrize("value", [-1, 1025, True, 2.0, "2"])
def test_bad_counts_are_explained(value):
    with pytest.raises(ConfigError) as caught:
        check_threads(value)
    assert str(caught.value) == (
        "num_threads must be 0 (auto: chosen for the model size) or a number of threads from 1 "
        f"to 1024, got {value!r}"
    )


# In a child process: thread counts are the process's, and the test process keeps its own.
CHILD = """
import json, os, threading
import cv2, faiss, torch
from threadpoolctl import threadpool_info
from pair_vpr_ros.model.threads import applied_threads, limit_this_thread
from pair_vpr_ros.weights import load_model

def pools():
    return sorted({i["num_threads"] for i in threadpool_info()})

seen = {}
load_model("random-tiny")  # auto: a light network runs on one thread
seen["auto"] = [applied_threads(), torch.get_num_threads(), torch.get_num_interop_threads(),
                cv2.getNumThreads(), pools()]

def build_thread():
    tid, pid = threading.get_native_id(), os.getpid()
    before = (faiss.omp_get_max_threads(), os.getpriority(os.PRIO_PROCESS, tid))
    limit_this_thread(background=True)
    seen["thread"] = [before[0], faiss.omp_get_max_threads(),
                      os.getpriority(os.PRIO_PROCESS, tid) - before[1]]

main_nice = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
worker = threading.Thread(target=build_thread)
worker.start()
worker.join()
seen["main nice"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) - main_nice
load_model("random-tiny", num_threads=2)  # explicit: as given, model or not
seen["two"] = [applied_threads(), torch.get_num_threads(), cv2.getNumThreads(), pools()]
print(json.dumps(seen))
"""


def test_every_pool_of_the_process_and_of_a_later_thread_gets_the_count():
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    done = subprocess.run(
        [sys.executable, "-c", CHILD], capture_output=True, text=True, env=env, timeout=120
    )
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.splitlines()[-1])
    # torch's pools, OpenCV's, and every OpenMP / OpenBLAS that threadpoolctl found
    assert seen["auto"] == [1, 1, 1, 1, [1]]
    # a thread started later had OpenMP's default (every core) until it took the count; a
    # background one runs 10 lower in priority, the main thread unchanged
    base = os.getpriority(os.PRIO_PROCESS, 0)  # the child's, inherited (nice 19 at most)
    lower = min(19, base + 10) - base if sys.platform.startswith("linux") else 0
    assert seen["thread"] == [usable_cores(), 1, lower]
    assert seen["main nice"] == 0
    assert seen["two"] == [2, 2, 2, [2]]
