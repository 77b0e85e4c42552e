"""Place map on Milvus beside the FAISS kinds, in one run: insert rate, query latency, recall.

The same trajectory-shaped 512-d descriptors (map_data.py) go into each index: FAISS flat /
hnsw / ivf (DescriptorIndex, as the map builds them) and a milvus-lite collection per Milvus
index type (MilvusIndex, as the map writes it: inserts of 2,000 rows, then `--single-adds` one
keyframe at a time). Queries are revisits, one per call, twice: unfiltered, and with the
temporal exclusion of a query stamped inside the map (a hole of `--exclude-frac` of the map:
FAISS gets the stamp mask, Milvus the filter expression). Every 10,000-keyframe session of the
data is its own session of one of 10 robots, so the filter's robot/session clause is evaluated
on every row: the hole applies to the query's own robot and session only. recall@k is against
the exact answer of the same query and rule (numpy, in chunks: no second copy of the map).
Figures depend on the machine and its load: the header prints both.

    python benchmarks/bench_milvus.py --sizes 1e5
    python benchmarks/bench_milvus.py --sizes 1e6 --kinds milvus-IVF_FLAT --db http://127.0.0.1:19530
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from map_data import trajectory, trajectory_queries
from tqdm import tqdm

from pair_vpr_ros.place_map import IndexConfig
from pair_vpr_ros.place_map.index import DescriptorIndex
from pair_vpr_ros.place_map.milvus.expr import ID_BITS, Exclusion
from pair_vpr_ros.place_map.milvus.index import MilvusIndex

KINDS = ("flat", "hnsw", "ivf", "milvus-HNSW", "milvus-IVF_FLAT", "milvus-FLAT")
BULK = 10_000  # rows handed to one add while building


def make_index(kind: str, n: int, db: str, dim: int, args):
    if not kind.startswith("milvus-"):
        return DescriptorIndex(dim, IndexConfig(kind=kind, train_at=min(25_000, n // 2)))
    config = IndexConfig(
        kind="milvus", milvus_uri=db, milvus_collection=f"bench_{kind[7:]}_{n}",
        milvus_index=kind[7:], nprobe=args.nprobe[-1], ef_search=args.ef_search,
        hnsw_m=args.hnsw_m, ef_construction=args.ef_construction,
    )  # fmt: skip
    index = MilvusIndex(dim, config, "bench")
    if index.client.has_collection(config.milvus_collection):  # a previous run's rows
        kept = index.client.query(config.milvus_collection, filter="pk >= 0", limit=1)
        if args.keep and kept and index._count("pk >= 0") >= n:
            index.unrecorded = False  # --keep: search that run's collection again
            return MilvusIndex(dim, config, "bench", writer=int(kept[0]["pk"]) >> ID_BITS)
        index.client.drop_collection(config.milvus_collection)
        index = MilvusIndex(dim, config, "bench")
    return index


SESSION = 10_000  # keyframes per session of map_data.trajectory
ROBOTS = 10


def identity(i: int) -> tuple[str, str]:
    """(robot, session) of keyframe i: its data session, driven by one of ROBOTS robots."""
    return f"r{(i // SESSION) % ROBOTS}", f"s{i // SESSION}"


def add(index, desc: np.ndarray, lo: int, like: int | None = None) -> None:
    """Keyframes lo.. (stamp = id, 1 s apart); `like`: identity of that keyframe instead."""
    ids = range(lo, lo + len(desc))
    index.add(desc, [(*identity(i if like is None else like), float(i)) for i in ids])


def build(kind: str, descs: np.ndarray, db: str, args) -> tuple:
    """-> (index, bulk rows/s, ms per single add, s to seal + index (Milvus))."""
    n, single = len(descs), min(args.single_adds, len(descs) // 10)
    index = make_index(kind, n, db, descs.shape[1], args)
    if isinstance(index, MilvusIndex) and not index.unrecorded:  # --keep: an earlier run's
        index._desc, index._synced = descs.copy(), n  # the map's own copy, as if it added them
        index._rows = [(*identity(i), float(i)) for i in range(n)]
        return index, np.nan, np.nan, settle(index, n, compact=False)
    t0 = time.perf_counter()
    for lo in tqdm(range(0, n - single, BULK), desc=f"{kind} add", leave=False):
        add(index, descs[lo : min(lo + BULK, n - single)], lo)
    bulk_rate = (n - single) / (time.perf_counter() - t0)
    t1 = time.perf_counter()
    for i in range(n - single, n):
        add(index, descs[i : i + 1], i)
    single_ms = (time.perf_counter() - t1) / max(single, 1) * 1e3
    seal_s = settle(index, n) if isinstance(index, MilvusIndex) else 0.0
    return index, bulk_rate, single_ms, seal_s


def settle(index, n: int, timeout_s: float = 3600.0, compact: bool = True) -> float:
    """Seal the segments, compact them (a kept collection: already done) and wait until every
    row is indexed and no index build is pending (else queries scan the unindexed rows brute
    force) -> seconds it took."""
    t0 = time.perf_counter()
    index.client.flush(index.collection)
    job = index.client.compact(index.collection) if compact else None
    while time.perf_counter() - t0 < timeout_s:
        info = index.client.describe_index(index.collection, "desc")
        done = job is None or index.client.get_compaction_state(job) == "Completed"
        if done and int(info.get("indexed_rows", 0)) >= n and not int(
            info.get("pending_index_rows", 0)
        ):  # fmt: skip
            break
        time.sleep(2.0)
    return time.perf_counter() - t0


def search_all(index, queries, k: int, rules) -> tuple[np.ndarray, np.ndarray]:
    """-> (ids [Q, k] -1 padded, wall ms [Q]); rules: per query None or (mask, Exclusion)."""
    ids, ms = np.full((len(queries), k), -1, np.int64), np.empty(len(queries))
    for i, (q, rule) in enumerate(zip(queries, rules, strict=True)):
        t0 = time.perf_counter()
        if rule is None:
            found, _ = index.search(q, k)
        elif isinstance(index, MilvusIndex):
            found, _ = index.search(q, k, exclusion=rule[1])
        else:
            found, _ = index.search(q, k, allowed=rule[0])
        ms[i] = (time.perf_counter() - t0) * 1e3
        ids[i, : len(found)] = found
    return ids, ms


def after_add_ms(index, descs: np.ndarray, queries, rules, k: int, reps: int = 20) -> float:
    """Median ms of a filtered search right after adding a keyframe, as the node does (rows
    past the map are re-added copies of its first ones: new ids, same descriptors)."""
    ms = []
    for i in range(reps):
        add(index, descs[i : i + 1], len(index), like=i)
        t0 = time.perf_counter()
        index.search(queries[i % len(queries)], k, exclusion=rules[i % len(rules)][1])
        ms.append((time.perf_counter() - t0) * 1e3)
    n = len(descs)  # the copies go again: the collection stays the map (--keep searches it)
    index.client.delete(index.collection, filter=f"pk >= {index.base + n}")
    index._rows, index._synced = index._rows[:n], n
    return float(np.median(ms))


def recall(ids: np.ndarray, exact: np.ndarray) -> float:
    return float(np.mean([len(set(a) & set(b)) / len(b) for a, b in zip(ids, exact, strict=True)]))


def temporal_rules(n: int, q: int, frac: float, rng) -> list:
    """Each query stamped inside the map (stamps = ids, 1 s apart) by the robot and session
    of the keyframe there: a hole of frac * n in its own session, the newest 10 left out
    -> per query (bool mask [n] of the eligible keyframes, the same rule as an Exclusion)."""
    ids = np.arange(n)
    rules = []
    for t in rng.uniform(0, n, q):
        robot, session = identity(int(t))
        own = ids // SESSION == int(t) // SESSION  # sessions are one robot's each
        mask = ~own | ((ids < n - 10) & (np.abs(ids - t) >= frac * n))
        rules.append((mask, Exclusion(float(t), frac * n, n - 10, robot, session)))
    return rules


def exact_answers(descs: np.ndarray, queries: np.ndarray, rules, k: int) -> tuple:
    """-> (ids [Q, k] unfiltered, ids [Q, k] under each query's rule): exact inner product."""
    plain, filt = np.empty((len(queries), k), np.int64), np.empty((len(queries), k), np.int64)
    for i, (q, rule) in enumerate(zip(queries, rules, strict=True)):
        sims = descs @ q
        plain[i] = np.argsort(-sims)[:k]
        sims[~rule[0]] = -np.inf
        filt[i] = np.argsort(-sims)[:k]
    return plain, filt


def bench_size(n: int, args, db: str) -> list[dict]:
    rng = np.random.default_rng(args.seed)
    descs, xy, city = trajectory(n, 512, rng, args.city_km)
    queries = trajectory_queries(city, xy, n, args.queries, np.random.default_rng(args.seed + 7))
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    rules = temporal_rules(n, args.queries, args.exclude_frac, np.random.default_rng(3))
    exact = exact_answers(descs, queries, rules, args.k)
    out = []
    for kind in args.kinds:
        index, rate, single_ms, seal_s = build(kind, descs, db, args)
        levels = args.consistency
        rows = []
        sweeps = [(lv, p) for lv in levels for p in args.nprobe]  # on the same collection
        for level, nprobe in sweeps if isinstance(index, MilvusIndex) else [("-", 0)]:
            set_level(index, level, nprobe)
            label = f"{kind} nprobe {nprobe}" if "IVF" in kind and len(args.nprobe) > 1 else kind
            plain, plain_ms = search_all(index, queries, args.k, [None] * len(queries))
            filt, filt_ms = search_all(index, queries, args.k, rules)
            rows.append(dict(
                n=n, kind=label, level=level, nprobe=nprobe, rate=rate, single_ms=single_ms,
                seal_s=seal_s,
                p50=np.median(plain_ms), p95=np.percentile(plain_ms, 95),
                rec=recall(plain, exact[0]), fp50=np.median(filt_ms),
                fp95=np.percentile(filt_ms, 95), frec=recall(filt, exact[1]), add_ms=np.nan,
            ))  # fmt: skip
        for row in rows:  # after every level's queries: the adds change the map a little
            if isinstance(index, MilvusIndex):
                set_level(index, row["level"], row["nprobe"])
                row["add_ms"] = after_add_ms(index, descs, queries, rules, args.k)
            print_row(row, args.k)
        out += rows
        if isinstance(index, MilvusIndex):
            index.unrecorded = False  # its rows go with the collection
            if not args.keep:
                index.client.drop_collection(index.collection)
            index.close()
        del index
    return out


def set_level(index, level: str, nprobe: int) -> None:
    if isinstance(index, MilvusIndex):
        index.config = replace(index.config, milvus_consistency=level, nprobe=nprobe)


def print_row(r: dict, k: int) -> None:
    print(
        f"| {r['n']:,} | {r['kind']} | {r['level']} | {r['rate']:,.0f} | {r['single_ms']:.2f} | "
        f"{r['seal_s']:.1f} | {r['p50']:.1f} | {r['p95']:.1f} | {r['rec']:.3f} | "
        f"{r['fp50']:.1f} | {r['fp95']:.1f} | {r['frec']:.3f} | {r['add_ms']:.1f} |",
        flush=True,
    )


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="1e5", help="map sizes, comma-separated (default 1e5)")
    p.add_argument("--kinds", default=",".join(KINDS), help=f"among {KINDS}")
    p.add_argument("--queries", type=int, default=100, help="queries per size (default 100)")
    p.add_argument("--k", type=int, default=10, help="top-k (default 10)")
    p.add_argument("--single-adds", type=int, default=200, help="last adds one at a time")
    p.add_argument(
        "--nprobe", default="32", help="milvus IVF_FLAT nprobe, comma-separated values are "
        "each timed on the same collection (default 32)",
    )  # fmt: skip
    p.add_argument("--ef-search", type=int, default=64, help="milvus HNSW ef (default 64)")
    p.add_argument("--hnsw-m", type=int, default=32, help="milvus HNSW M (default 32)")
    p.add_argument(
        "--ef-construction", type=int, default=80, help="milvus HNSW efConstruction (default 80)"
    )
    p.add_argument("--exclude-frac", type=float, default=0.1, help="temporal hole / map size")
    p.add_argument("--city-km", type=float, default=3.0, help="map_data city size (default 3)")
    p.add_argument(
        "--db", help="milvus_uri: a milvus-lite file or a server (default: a temporary file)"
    )
    p.add_argument(
        "--consistency", default="Bounded,Session,Strong",
        help="milvus_consistency levels to time queries with (default all three)",
    )  # fmt: skip
    p.add_argument(
        "--keep", action="store_true",
        help="keep each Milvus collection after the run, and search a kept one of the right "
        "size again instead of rebuilding it (a 1e6 build takes ~20-40 min on 2 cores)",
    )  # fmt: skip
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    args.sizes = [int(float(s)) for s in args.sizes.split(",")]
    args.kinds = args.kinds.split(",")
    args.consistency = args.consistency.split(",")
    args.nprobe = [int(v) for v in args.nprobe.split(",")]
    if not set(args.kinds) <= set(KINDS):
        p.error(f"--kinds must be among {KINDS}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import pymilvus

    cpu = platform.processor() or platform.machine()
    now = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    print(
        f"{now}, {cpu}, {os.cpu_count()} cpus, load average {os.getloadavg()[0]:.1f}, pymilvus "
        f"{pymilvus.__version__}, k {args.k}, {args.queries} queries, milvus HNSW ef "
        f"{args.ef_search} M {args.hnsw_m} efConstruction {args.ef_construction}, IVF_FLAT "
        f"nprobe {args.nprobe}"
    )
    print(
        "\n| keyframes | index | consistency | bulk insert rows/s | single add ms | seal+index s "
        "| "
        f"query p50 ms | p95 ms | recall@{args.k} | filtered p50 ms | filtered p95 ms | "
        f"filtered recall@{args.k} | filtered p50 ms right after an add |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="bench-milvus-") as tmp:
        db = args.db or str(Path(tmp) / "bench.db")  # any milvus_uri: a server too
        for n in args.sizes:
            bench_size(n, args, db)
    print(f"\nload average after: {os.getloadavg()[0]:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
