"""CPU threads of the network and the libraries beside it: one count for the process.

Five thread pools run a keyframe on a CPU: torch's intra-op pool (OpenMP, MKL), torch's
inter-op pool, the BLAS and OpenMP runtimes that numpy, OpenCV and FAISS each bring, OpenCV's
own pool (SIFT, ORB, RANSAC) and OpenVINO's inference threads. Left alone, each takes every
core. The node parameter ``num_threads``, ``pairvpr-bag-replay --threads`` and the benchmarks'
``--threads`` set them all to one count (`apply_threads`: torch, threadpoolctl, OpenCV; the
OpenVINO graphs are compiled with it), before the network runs.

``AUTO`` (0) picks the count by measurement (docs/performance.md, "Sharing the CPU"): a light
network (below `LIGHT_GMAC` per encode, such as the demo model) runs on one thread, whose small
tensors gain nothing from a second core but the cost of waking it; a ViT-B-sized one on every
core the process may use.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading

import torch

from pair_vpr_ros.errors import ConfigError
from pair_vpr_ros.model.config import ModelConfig

AUTO = 0
MAX_THREADS = 1024
# Encoders below this many GMAC an image run on one thread (demo model 0.05, ViT-B/322 45).
LIGHT_GMAC = 1.0
_applied: list[int] = []  # the count apply_threads set last (empty: never called)
_local = threading.local()  # what limit_this_thread did in each thread


def usable_cores() -> int:
    """CPUs this process may run on (its affinity mask: a container's or taskset's limit)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def encode_gmac(config: ModelConfig) -> float:
    """Multiply-adds of one encode in GMAC: the encoder blocks' linear layers over the patch,
    class and register tokens (attention adds a few per cent at these sizes)."""
    d, hidden = config.embed_dim, config.mlp_hidden
    per_token = 4 * d * d + (3 if config.swiglu else 2) * d * hidden
    tokens = config.num_patches + 1 + config.num_registers
    return config.depth * tokens * per_token / 1e9


def auto_threads(config: ModelConfig, cores: int | None = None) -> int:
    """The measured default for `config`: 1 for a light network, else every usable core."""
    return 1 if encode_gmac(config) < LIGHT_GMAC else (cores or usable_cores())


def check_threads(value: int, name: str = "num_threads") -> int:
    """`value` as a thread count: 0 (auto) or 1..MAX_THREADS; ConfigError otherwise."""
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_THREADS:
        raise ConfigError(
            f"{name} must be 0 (auto: chosen for the model size) or a number of threads from 1 "
            f"to {MAX_THREADS}, got {value!r}"
        )
    return value


def resolve_threads(requested: int, config: ModelConfig) -> int:
    """`requested` (0: `auto_threads(config)`) -> the count to run on."""
    return check_threads(requested) or auto_threads(config)


def apply_threads(count: int) -> None:
    """Run this process's pools on `count` threads: torch intra-op (and MKL), torch inter-op
    (1: the pipeline runs no inter-op work, and the pool can only be sized before its first
    use), OpenCV, and through threadpoolctl every OpenBLAS and OpenMP runtime loaded (numpy's,
    OpenCV's, FAISS's: imported here first so that they are). OpenMP counts belong to the
    calling thread: threads started later call `limit_this_thread` (the node's map and build
    threads). OpenVINO takes the count when it compiles (`OpenVINOModel(threads=...)`)."""
    import cv2
    import faiss  # noqa: F401 - loaded so that threadpoolctl finds its OpenMP and BLAS
    from threadpoolctl import threadpool_limits

    count = check_threads(count) or usable_cores()
    torch.set_num_threads(count)
    with contextlib.suppress(RuntimeError):  # sized already (its first use, an earlier call)
        torch.set_num_interop_threads(1)
    cv2.setNumThreads(count)
    threadpool_limits(count)
    _applied[:] = [count]


def applied_threads() -> int | None:
    """The count `apply_threads` set, None when it has not run in this process."""
    return _applied[0] if _applied else None


def limit_this_thread(background: bool = False) -> None:
    """Call in a thread that runs the model and was started after `apply_threads` (once is
    enough; again is free): its OpenMP runtimes (FAISS's, OpenBLAS's OpenMP build; torch sets
    its own) get the process's count, which OpenMP keeps per thread. `background` (a map build
    beside the live frames) also lowers the thread's priority by 10 on Linux, where the pools
    it starts inherit it: the build takes the cores the live pipeline leaves instead of
    slowing it down."""
    done = getattr(_local, "done", None)
    if done == (applied_threads(), background):
        return
    if _applied:
        from threadpoolctl import threadpool_limits

        threadpool_limits(_applied[0], user_api="openmp")
    if background and sys.platform.startswith("linux"):
        tid = threading.get_native_id()  # Linux: a priority per thread
        with contextlib.suppress(OSError):
            lower = min(19, os.getpriority(os.PRIO_PROCESS, tid) + 10)
            os.setpriority(os.PRIO_PROCESS, tid, lower)
    _local.done = (applied_threads(), background)
