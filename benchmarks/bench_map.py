"""Place map benchmark: FAISS add/search cost (exact vs HNSW), HNSW recall, bytes per keyframe.

Descriptors are synthetic but structured like learned ones: x = normalise(A z + noise) with
z ~ N(0, I_64) (intrinsic dimension 64 in 512-d); queries are revisits (database vector + noise).
Search is timed one query at a time, as the loop detector issues them; prints Markdown tables.

    python benchmarks/bench_map.py --sizes 1e3,1e4,1e5,1e6 --dense-shape 529,768
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import faiss
import numpy as np
from tqdm import tqdm

from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.index import DescriptorIndex


def make_descriptors(n: int, dim: int, rng: np.random.Generator, basis: np.ndarray) -> np.ndarray:
    """-> [n, dim] float32 unit vectors with low intrinsic dimension."""
    out = np.empty((n, dim), np.float32)
    for lo in range(0, n, 100_000):
        z = rng.standard_normal((min(n, lo + 100_000) - lo, basis.shape[0]), dtype=np.float32)
        x = z @ basis + 0.05 * rng.standard_normal((len(z), dim), dtype=np.float32)
        out[lo : lo + len(z)] = x / np.linalg.norm(x, axis=1, keepdims=True)
    return out


def time_searches(index: DescriptorIndex, queries: np.ndarray, k: int, max_id: int | None):
    """-> (ids [Q, k], latencies [Q] seconds), one query per call."""
    ids, lat = np.full((len(queries), k), -1, np.int64), np.empty(len(queries))
    for i, q in enumerate(queries):
        t0 = time.perf_counter()
        found, _ = index.search(q, k, max_id)
        lat[i] = time.perf_counter() - t0
        ids[i, : len(found)] = found
    return ids, lat


def bench_size(n, descs, queries, args, kinds) -> list[dict]:
    """Build each index kind over descs[:n]; -> one result row per kind."""
    rows, exact_ids = [], None
    for kind in kinds:
        config = IndexConfig(
            kind=kind,
            hnsw_m=args.hnsw_m,
            ef_construction=args.ef_construction,
            ef_search=args.ef_search,
            exact_below=0,
        )
        index = DescriptorIndex(descs.shape[1], config)
        n_single = min(args.single_adds, n)
        t0 = time.perf_counter()
        for lo in tqdm(range(0, n - n_single, 50_000), desc=f"{kind} {n:.0e}", leave=False):
            index.add(descs[lo : min(lo + 50_000, n - n_single)])
        build = time.perf_counter() - t0
        t0 = time.perf_counter()
        for row in descs[n - n_single : n]:  # the live map adds one keyframe at a time
            index.add(row[None])
        single = (time.perf_counter() - t0) / max(n_single, 1)
        ids, lat = time_searches(index, queries, args.k, None)
        _, lat_ex = time_searches(index, queries, args.k, n - 1 - args.exclude)
        if kind == "flat":
            exact_ids = ids
        recall = top1 = np.nan
        if exact_ids is not None:
            hits = [len(set(a) & set(b)) for a, b in zip(ids, exact_ids, strict=True)]
            recall = float(np.mean(hits)) / args.k
            top1 = float(np.mean(ids[:, 0] == exact_ids[:, 0]))
        rows.append(
            dict(n=n, kind=kind, build=build + single * n_single, single_us=single * 1e6,
                 med=np.median(lat) * 1e3, p95=np.percentile(lat, 95) * 1e3,
                 med_ex=np.median(lat_ex) * 1e3, recall=recall, top1=top1)
        )  # fmt: skip
        del index
    return rows


def bytes_per_keyframe(args, dim: int, shape: tuple[int, int]) -> dict[str, float]:
    """Save a small map with full-size dense tokens; -> bytes per keyframe of each file."""
    rng = np.random.default_rng(args.seed + 1)
    n = args.mem_keyframes
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(dir=args.work_dir) as tmp:
        for kind in ("flat", "hnsw"):
            with PlaceMap(dim, shape, "bench", index=kind, work_dir=tmp) as m:
                descs = make_descriptors(n, dim, rng, rng.standard_normal((64, dim), np.float32))
                dense = rng.standard_normal(shape, dtype=np.float32)
                pose = (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)
                for i in range(n):
                    meta = KeyframeMeta(stamp=1e9 + i, frame_id="camera", pose=pose, source="run1")
                    m.add(descs[i], dense + i, meta)
                d = Path(tmp) / f"map-{kind}"
                t0 = time.perf_counter()
                m.save(d)
                out[f"save_{kind}_s"] = time.perf_counter() - t0
                t0 = time.perf_counter()
                m.get_dense(list(range(min(10, n))))
                out["get_dense10_ms"] = (time.perf_counter() - t0) * 1e3
            for f in os.listdir(d):
                role = f.split("-")[0] + ("_crc" if f.endswith(".crc") else "")
                if role in ("index", "meta", "dense", "dense_crc"):
                    key = f"{role}_{kind}" if role == "index" else role
                    out[key] = os.path.getsize(d / f) / n
    return out


def _fmt(value: float) -> str:
    return "-" if np.isnan(value) else f"{value:.3f}"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", default="1e3,1e4,1e5,1e6", help="map sizes, comma separated")
    p.add_argument("--dim", type=int, default=512, help="descriptor dimension")
    p.add_argument("--dense-shape", default="529,768", help="N,D dense tokens per keyframe")
    p.add_argument("--kinds", default="flat,hnsw", help="index kinds to time (flat gives recall)")
    p.add_argument("--queries", type=int, default=200, help="single queries timed per size")
    p.add_argument("--k", type=int, default=10, help="neighbours per query (recall@k)")
    p.add_argument("--exclude", type=int, default=100, help="recent ids excluded (max_id column)")
    p.add_argument("--hnsw-m", type=int, default=32, help="HNSW M")
    p.add_argument("--ef-construction", type=int, default=80, help="HNSW efConstruction")
    p.add_argument("--ef-search", type=int, default=64, help="HNSW efSearch")
    p.add_argument("--single-adds", type=int, default=200, help="adds timed one at a time")
    p.add_argument("--threads", type=int, default=0, help="FAISS OpenMP threads (0: default)")
    p.add_argument("--mem-keyframes", type=int, default=64, help="keyframes in the saved map")
    p.add_argument("--work-dir", default=None, help="folder for the saved test map")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        sizes = sorted(int(float(s)) for s in args.sizes.split(","))
        shape = tuple(int(v) for v in args.dense_shape.split(","))
        kinds = args.kinds.split(",")
        assert len(shape) == 2 and set(kinds) <= {"flat", "hnsw"} and min(sizes) > args.exclude
    except (ValueError, AssertionError):
        print("error: bad --sizes, --dense-shape or --kinds (sizes must exceed --exclude)",
              file=sys.stderr)  # fmt: skip
        return 2
    if args.threads:
        faiss.omp_set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    basis = rng.standard_normal((64, args.dim), dtype=np.float32)
    descs = make_descriptors(max(sizes), args.dim, rng, basis)
    picks = rng.integers(0, min(sizes), args.queries)
    queries = descs[picks] + 0.02 * rng.standard_normal((args.queries, args.dim), np.float32)
    print(f"faiss {faiss.__version__}, omp threads {faiss.omp_get_max_threads()}, "
          f"cpus {os.cpu_count()}, dim {args.dim}, k {args.k}, HNSW M={args.hnsw_m} "
          f"efConstruction={args.ef_construction} efSearch={args.ef_search}\n")  # fmt: skip
    print("| keyframes | index | build s | add µs (single) | search ms median | p95 | "
          f"median, max_id=n-{args.exclude + 1} | recall@{args.k} | top-1 = exact |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for n in sizes:
        for r in bench_size(n, descs, queries, args, kinds):
            print(f"| {r['n']:.0e} | {r['kind']} | {r['build']:.1f} | {r['single_us']:.0f} | "
                  f"{r['med']:.3f} | {r['p95']:.3f} | {r['med_ex']:.3f} | "
                  f"{_fmt(r['recall'])} | {_fmt(r['top1'])} |", flush=True)  # fmt: skip
    mem = bytes_per_keyframe(args, args.dim, shape)
    print(f"\nBytes per keyframe (saved map of {args.mem_keyframes}, dense {shape} float16):\n")
    print("| file | bytes/keyframe |\n|---|---|")
    for key in ("dense", "dense_crc", "index_flat", "index_hnsw", "meta"):
        print(f"| {key} | {mem.get(key, 0):,.0f} |")
    total = mem["dense"] + mem["dense_crc"] + mem["meta"]
    print(f"| total (flat / hnsw) | {total + mem['index_flat']:,.0f} / "
          f"{total + mem['index_hnsw']:,.0f} |")  # fmt: skip
    print(f"\nsave: flat {mem['save_flat_s']:.2f} s, hnsw {mem['save_hnsw_s']:.2f} s; "
          f"get_dense(10 ids) {mem['get_dense10_ms']:.2f} ms")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
