"""Place map benchmark: add/search cost of each index kind (flat, hnsw, ivf), recall, memory.

Two kinds of synthetic 512-d descriptors (`--data`, both by default; map_data.py):
``trajectory`` (sessions of random walks through a city: what a robot's map looks like) and
``lowrank`` (an unstructured 64-d cloud).

Search is timed one query at a time on one thread, as the loop detector issues them; each HNSW
graph is built once per M and searched at every `--ef-search`; each `ivf` index (the place map's
own kind, built through DescriptorIndex as the map builds it: exact below `--train-at`, trained
on the add that reaches it and again at 4x) once per `--ivf-nlist` and searched at every
`--nprobe`; its trainings (the one-off pauses of the add that triggers them) are printed.
recall@k is against the exact (flat) search. `--extrapolate N` fits recall and median time
against log10(size) over the sizes run (least squares, per M / efSearch) and prints the fit at
N: a fit, not a measurement.

    python benchmarks/bench_map.py --sizes 1e4,3e4,1e5 --ef-search 64,128,256 --extrapolate 1e6
    python benchmarks/bench_map.py --data trajectory --sizes 1e6 --hnsw-max 0 --nprobe 16,32,64
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import faiss
import numpy as np
from bench_map_growth import work_folder
from map_data import lowrank, trajectory, trajectory_queries
from tqdm import tqdm

from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.index import DescriptorIndex


def time_searches(index: DescriptorIndex, queries: np.ndarray, k: int, max_id: int | None):
    """-> (ids [Q, k], latencies [Q, 2] seconds: wall, CPU of this thread), one query per call.

    On one search thread the CPU time is the search's own work: on a shared machine it is not
    inflated by waiting for a core, the wall time is (compare the two)."""
    ids, lat = np.full((len(queries), k), -1, np.int64), np.empty((len(queries), 2))
    for i, q in enumerate(queries):
        t0, c0 = time.perf_counter(), time.thread_time()
        found, _ = index.search(q, k, max_id)
        lat[i] = time.perf_counter() - t0, time.thread_time() - c0
        ids[i, : len(found)] = found
    return ids, lat


BULK = 25_000  # adds of this many: ivf then trains at its own sizes (25,000 x 4^s)


def build(descs: np.ndarray, config: IndexConfig, single_adds: int) -> tuple:
    """Index over descs (the last `single_adds` one at a time, as the live map adds) ->
    (index, build s, µs per single add); prints each ivf training. index.rss_growth: bytes per
    keyframe by which the process's resident memory grew (allocator slack and list capacity
    included; approximate: freed memory is not always returned to the system)."""
    rss0 = resident_bytes()
    index, n = DescriptorIndex(descs.shape[1], config), len(descs)
    n_single = min(single_adds, n)
    t0, trained = time.perf_counter(), None
    for lo in tqdm(range(0, n - n_single, BULK), desc=f"{config.kind} {n:.0e}", leave=False):
        c0 = time.process_time()
        index.add(descs[lo : min(lo + BULK, n - n_single)])
        if index.last_training is not trained:
            trained = index.last_training
            print(f"  ivf training at {trained.keyframes:,} keyframes: {trained.nlist} lists, "
                  f"k-means on {trained.sample:,}: {trained.seconds:.1f} s wall, "
                  f"{time.process_time() - c0:.1f} s CPU (all threads)", flush=True)  # fmt: skip
    bulk = time.perf_counter() - t0
    t0 = time.perf_counter()
    for row in descs[n - n_single :]:
        index.add(row[None])
    single = (time.perf_counter() - t0) / max(n_single, 1)
    index.rss_growth = (resident_bytes() - rss0) / max(n, 1)
    return index, bulk + single * n_single, single * 1e6


def resident_bytes() -> int:
    """This process's resident memory (VmRSS of /proc/self/status; 0 where there is none)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def bench_size(n, descs, queries, args) -> list[dict]:
    """Flat (exact), then one HNSW graph per M searched at every efSearch, then one ivf index
    per nlist searched at every nprobe -> result rows."""
    flat, build_s, single = build(descs[:n], IndexConfig(kind="flat"), args.single_adds)
    exact, lat = time_searches(flat, queries, args.k, newest(n, args))
    rows = [row(n, "flat", 0, 0, build_s, single, lat, 1.0, 1.0, flat)]
    del flat
    for m in args.hnsw_m if n <= args.hnsw_max else ():
        config = IndexConfig(kind="hnsw", hnsw_m=m, ef_construction=args.ef_construction,
                             ef_search=args.ef_search[0], exact_below=0)  # fmt: skip
        rows += sweep(descs[:n], queries, exact, config, "ef_search", args.ef_search, args)
    for nlist in args.ivf_nlist:
        config = IndexConfig(kind="ivf", nlist=nlist, nprobe=args.nprobe[0],
                             train_at=args.train_at, retrain_growth=args.retrain_growth,
                             exact_below=0)  # fmt: skip
        rows += sweep(descs[:n], queries, exact, config, "nprobe", args.nprobe, args)
    return rows


def sweep(descs, queries, exact, config: IndexConfig, field: str, values, args) -> list[dict]:
    """Build one index, then search it with `field` (ef_search / nprobe) at each value."""
    index, build_s, single = build(descs, config, args.single_adds)
    shape = config.hnsw_m if config.kind == "hnsw" else "flat"
    if config.kind == "ivf" and index.last_training:
        shape = index._index.nlist  # lists of the last training
    rows = []
    for value in values:
        index.config = replace(config, **{field: value})
        ids, lat = time_searches(index, queries, args.k, newest(len(descs), args))
        hits = [len(set(a) & set(b)) for a, b in zip(ids, exact, strict=True)]
        recall, top1 = float(np.mean(hits)) / args.k, float(np.mean(ids[:, 0] == exact[:, 0]))
        rows.append(row(len(descs), config.kind, shape, value, build_s, single, lat, recall,
                        top1, index))  # fmt: skip
    return rows


def newest(n: int, args) -> int | None:
    """max_id of the searches: the newest `--exclude-recent` keyframes are not eligible."""
    return n - 1 - args.exclude_recent if args.exclude_recent else None


def row(n, kind, m, ef, build_s, single_us, lat, recall, top1, index) -> dict:
    size = faiss.serialize_index(index._index).nbytes / max(len(index), 1)
    return dict(n=n, kind=kind, m=m, ef=ef, build=build_s, single_us=single_us,
                med=np.median(lat[:, 0]) * 1e3, p95=np.percentile(lat[:, 0], 95) * 1e3,
                cpu=np.median(lat[:, 1]) * 1e3, cpu95=np.percentile(lat[:, 1], 95) * 1e3,
                recall=recall, top1=top1, bytes=size, rss=index.rss_growth)  # fmt: skip


def print_rows(rows: list[dict], k: int, header: bool) -> None:
    if header:
        print(f"| keyframes | index | M (ivf: lists) | efSearch (ivf: nprobe) | build s "
              "| add µs (single) | search ms median | p95 | CPU ms median | CPU p95 "
              f"| recall@{k} | top-1 = exact | index B/keyframe (file) | RAM growth B/keyframe "
              "|")  # fmt: skip
        print("|---" * 14 + "|")
    for r in rows:
        m, ef = (r["m"], r["ef"]) if r["kind"] != "flat" else ("-", "-")
        print(f"| {r['n']:.0e} | {r['kind']} | {m} | {ef} | {r['build']:.1f} | "
              f"{r['single_us']:.0f} | {r['med']:.3f} | {r['p95']:.3f} | {r['cpu']:.3f} | "
              f"{r['cpu95']:.3f} | {r['recall']:.3f} | "
              f"{r['top1']:.3f} | {r['bytes']:,.0f} | {r['rss']:,.0f} |", flush=True)  # fmt: skip


def extrapolate(rows: list[dict], target: int) -> None:
    """Least-squares lines of recall and median time against log10(size), per (M, efSearch)."""
    print(f"\nExtrapolated to {target:.0e} (a fit over the sizes above, not a measurement):\n")
    print("| M | efSearch | sizes fitted | recall@k at target | median ms at target |")
    print("|---|---|---|---|---|")
    for m, ef in sorted({(r["m"], r["ef"]) for r in rows if r["kind"] == "hnsw"}):
        pts = [r for r in rows if (r["kind"], r["m"], r["ef"]) == ("hnsw", m, ef)]
        if len(pts) < 2:
            continue
        x = np.log10([r["n"] for r in pts])
        rec = np.polyval(np.polyfit(x, [r["recall"] for r in pts], 1), np.log10(target))
        med = np.polyval(np.polyfit(x, [r["med"] for r in pts], 1), np.log10(target))
        print(f"| {m} | {ef} | {len(pts)} | {min(rec, 1.0):.3f} | {med:.2f} |")


def bytes_per_keyframe(args, dim: int, shape: tuple[int, int]) -> dict[str, float]:
    """Save a small map with full-size dense tokens; -> bytes per keyframe of each file (ivf
    trained at 39 keyframes, one list: its centroids cost nlist x dim x 4 B more in all)."""
    rng = np.random.default_rng(args.seed + 1)
    n = args.mem_keyframes
    out: dict[str, float] = {}
    kinds = {"flat": "flat", "hnsw": "hnsw", "ivf": IndexConfig(kind="ivf", train_at=39)}
    with tempfile.TemporaryDirectory(dir=args.work_dir) as tmp:
        for kind, config in kinds.items():
            with PlaceMap(dim, shape, "bench", index=config, work_dir=tmp) as m:
                descs = lowrank(n, dim, rng, rng.standard_normal((64, dim), np.float32))
                dense = rng.standard_normal(shape, dtype=np.float32)
                pose = (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)
                for i in range(n):
                    meta = KeyframeMeta(stamp=1e9 + i, frame_id="camera", pose=pose, source="run1")
                    m.add(descs[i], dense + i, meta)
                d = Path(tmp) / f"map-{kind}"
                m.save(d)
            for f in os.listdir(d):  # map-g.sqlite: the store (rows with descriptors)
                role = {"map": "store"}.get(f.split("-")[0], f.split("-")[0])
                if role in ("index", "store", "dense") and f.split(".")[-1] != "lock":
                    key = f"{role}_{kind}" if role in ("index", "store") else role
                    out[key] = os.path.getsize(d / f) / n
    return out


def ints(text: str) -> list[int]:
    return [int(float(v)) for v in text.split(",")]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--sizes",
        type=ints,
        default=[10**3, 10**4, 10**5],
        help="map sizes, comma "
        "separated (1e6 needs ~5 GB of RAM and hours of HNSW build on 2 cores)",
    )
    p.add_argument("--data", default="trajectory,lowrank", help="descriptor kinds (see above)")
    p.add_argument("--dim", type=int, default=512, help="descriptor dimension")
    p.add_argument("--dense-shape", default="529,768", help="N,D dense tokens per keyframe")
    p.add_argument("--queries", type=int, default=200, help="single queries timed per size")
    p.add_argument("--k", type=int, default=10, help="neighbours per query (recall@k)")
    p.add_argument("--hnsw-m", type=ints, default=[32], help="HNSW M values (one build each)")
    p.add_argument(
        "--hnsw-max",
        type=lambda v: int(float(v)),
        default=10**6,
        help="build HNSW only up to this size (its build is the slow part)",
    )
    p.add_argument("--ef-construction", type=int, default=80, help="HNSW efConstruction")
    p.add_argument("--ef-search", type=ints, default=[64, 128, 256], help="HNSW efSearch values")
    p.add_argument("--ivf-nlist", type=lambda v: ints(v) if v else [], default=[0],
                   help="ivf list counts, one build each (0: the map's default, 4 sqrt(n) at "
                   "each training; '': no ivf)")  # fmt: skip
    p.add_argument("--nprobe", type=ints, default=[16, 32, 64], help="ivf lists searched")
    p.add_argument("--train-at", type=lambda v: int(float(v)), default=25_000,
                   help="ivf: exact search below this many keyframes, then trained")  # fmt: skip
    p.add_argument("--retrain-growth", type=float, default=4.0,
                   help="ivf: train again at this factor of growth (0: never)")  # fmt: skip
    p.add_argument("--exclude-recent", type=int, default=0, help="searches exclude the newest "
                   "N keyframes (max_id, a range selector, as the loop detector's recency "
                   "window); 0: no selector")  # fmt: skip
    p.add_argument("--single-adds", type=int, default=200, help="adds timed one at a time")
    p.add_argument("--city-km", type=float, default=5.0, help="trajectory data: city side, km")
    p.add_argument("--extrapolate", type=lambda v: int(float(v)), help="fit recall / time to "
                   "this size (e.g. 1e6) from the sizes run")  # fmt: skip
    p.add_argument("--threads", type=int, default=0, help="FAISS OpenMP threads for building")
    p.add_argument("--mem-keyframes", type=int, default=64, help="keyframes in the saved map")
    p.add_argument("--work-dir", default=None, help="folder for the saved test map")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    args = p.parse_args(argv)
    work_folder(p, args.work_dir)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    shape = tuple(int(v) for v in args.dense_shape.split(","))
    kinds = args.data.split(",")
    if len(shape) != 2 or not set(kinds) <= {"trajectory", "lowrank"} or min(args.sizes) < 100:
        print("error: bad --dense-shape, --data or --sizes (>= 100)", file=sys.stderr)
        return 2
    if args.threads:
        faiss.omp_set_num_threads(args.threads)
    print(f"faiss {faiss.__version__}, build threads {faiss.omp_get_max_threads()}, search "
          f"threads 1, cpus {os.cpu_count()}, dim {args.dim}, k {args.k}, efConstruction "
          f"{args.ef_construction}, {args.queries} queries per size")  # fmt: skip
    for kind in kinds:
        rng = np.random.default_rng(args.seed)
        n_max = max(args.sizes)
        if kind == "trajectory":
            descs, xy, city = trajectory(n_max, args.dim, rng, args.city_km)
        else:
            basis = rng.standard_normal((64, args.dim), dtype=np.float32)
            descs = lowrank(n_max, args.dim, rng, basis)
        rows = []
        print(f"\n### {kind} descriptors\n")
        for n in sorted(args.sizes):
            qrng = np.random.default_rng(args.seed + 7)
            if kind == "trajectory":
                queries = trajectory_queries(city, xy, n, args.queries, qrng)
            else:
                picks = qrng.integers(0, n, args.queries)
                noise = 0.02 * qrng.standard_normal((args.queries, args.dim), np.float32)
                queries = descs[picks] + noise
            new = bench_size(n, descs, queries, args)
            print_rows(new, args.k, header=not rows)
            rows += new
        if args.extrapolate:
            extrapolate(rows, args.extrapolate)
    mem = bytes_per_keyframe(args, args.dim, shape)
    print(f"\nBytes per keyframe (saved map of {args.mem_keyframes}, dense {shape} q4):\n")
    print("| file | bytes/keyframe |\n|---|---|")
    keys = ("dense", "store_flat", "index_hnsw", "index_ivf")  # flat: no index file
    for key in keys:
        print(f"| {key} | {mem.get(key, 0):,.0f} |")
    total = mem["dense"] + mem["store_flat"]
    print(f"| total (flat / hnsw M=32 / ivf) | {total:,.0f} / "
          f"{total + mem['index_hnsw']:,.0f} / {total + mem['index_ivf']:,.0f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
