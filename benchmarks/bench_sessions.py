"""Recent-keyframe exclusion per robot-session (issue 22): the cost of `GroupedRecency.eligible`
and of the FAISS search each form of its answer gives, against the number of sessions.

A map of `--size` keyframes (random unit 512-d descriptors, flat index) recorded in `--sessions`
sessions one after another, all on the same clock (each session's stamps start at 0: the worst
case for the old, session-blind exclusion). Three queries, timed one at a time on one thread:

* live: the newest session (what a running node asks): a prefix, as before issue 22;
* middle: a session in the middle of the map (a loaded map continued in its own session):
  all ids but one range (`IDSelectorNot`);
* interleaved: every session's keyframes alternate (`--sessions` robots mapping at once into
  one map): the session's own recent keyframes are scattered, a bitmap.

    python benchmarks/bench_sessions.py --size 100000 --sessions 1,10,100
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from pair_vpr_ros.loops.recency import GroupedRecency
from pair_vpr_ros.place_map import PlaceMap


def build(size: int, dim: int, seed: int = 0) -> PlaceMap:
    rng = np.random.default_rng(seed)
    desc = rng.normal(size=(size, dim)).astype(np.float32)
    m = PlaceMap(desc_dim=dim, dense_shape=(1, 1))
    # descriptors only (no dense tokens or metadata: only the search is timed)
    m._index.add(desc / np.linalg.norm(desc, axis=1, keepdims=True))
    return m


def keyframes(size: int, sessions: int, interleaved: bool):
    per = size // sessions
    for i in range(size):
        s, j = (i % sessions, i // sessions) if interleaved else (i // per, i % per)
        yield i, float(j), "r", f"s{min(s, sessions - 1)}"


def timed(fn, repeat: int) -> float:
    """Median milliseconds of `fn()`."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


def search(m: PlaceMap, query: np.ndarray, ok, k: int):
    if ok.prefix is not None:
        return m.search(query, k, max_id=ok.prefix - 1)
    return m.search(query, k, allowed=ok.mask, exclude=ok.exclude)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=100_000, help="keyframes in the map")
    p.add_argument("--sessions", default="1,10,100", help="comma-separated session counts")
    p.add_argument("--dim", type=int, default=512, help="descriptor size")
    p.add_argument("--repeat", type=int, default=20, help="timed repetitions (median)")
    args = p.parse_args()
    m = build(args.size, args.dim)
    query = np.random.default_rng(1).normal(size=args.dim).astype(np.float32)
    print(f"{args.size} keyframes, flat index, k=10, exclude 30 s / 10 keyframes, median ms")
    print(f"{'sessions':>8} {'query':>12} {'form':>8} {'eligible':>9} {'select':>8} {'search':>8}")
    for sessions in (int(s) for s in args.sessions.split(",")):
        for name, interleaved, who in (
            ("live", False, f"s{sessions - 1}"),
            ("middle", False, f"s{sessions // 2}"),
            ("interleaved", True, "s0"),
        ):
            if sessions == 1 and name != "live":
                continue
            recency = GroupedRecency(keyframes(args.size, sessions, interleaved))
            stamp = float(args.size // sessions)  # just after the session's last keyframe
            ok = recency.eligible(stamp, "r", who, 30.0, 10)
            form = "prefix" if ok.prefix is not None else "range" if ok.exclude else "bitmap"
            select = timed(lambda r=recency, s=stamp, w=who: r.eligible(s, "r", w, 30.0, 10), 20)
            found = timed(lambda o=ok: search(m, query, o, 10), args.repeat)
            print(f"{sessions:>8} {name:>12} {form:>8} {ok.count:>9} {select:>8.3f} {found:>8.2f}")
    m.close()


if __name__ == "__main__":
    main()
