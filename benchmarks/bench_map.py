"""Place map benchmark: FAISS add/search cost (exact vs HNSW), HNSW recall, bytes per keyframe.

Two kinds of synthetic 512-d descriptors (`--data`, both by default):

- ``trajectory``: what a robot's map looks like. Sessions of 10,000 keyframes drive smooth
  random walks (1 m per keyframe) over a square city of `--city-km`; a place's descriptor is a
  smooth random field of its position (random Fourier features at 15 m, 150 m and 1.5 km length
  scales, 60/30/10 % of the variance) plus a per-session appearance offset (a quarter of the
  place signal's variance) and per-frame noise, so consecutive keyframes are near-duplicates,
  sessions form clusters, and routes revisit each other. Queries are revisits: a database
  keyframe's position moved up to 2 m, seen in a new session's appearance.
- ``lowrank``: x = normalise(A z + noise), z ~ N(0, I_64): no trajectory structure at all, an
  unstructured 64-d cloud (the earlier benchmark's data). Queries: database vector + noise.

Search is timed one query at a time on one thread, as the loop detector issues them; each HNSW
graph is built once per M and searched at every `--ef-search`; recall@k is against the exact
(flat) search. `--extrapolate N` fits recall and median time against log10(size) over the sizes
run (least squares, per M / efSearch) and prints the fit at N: a fit, not a measurement.

    python benchmarks/bench_map.py --sizes 1e4,3e4,1e5 --ef-search 64,128,256 --extrapolate 1e6
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
from tqdm import tqdm

from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.index import DescriptorIndex


def lowrank(n: int, dim: int, rng: np.random.Generator, basis: np.ndarray) -> np.ndarray:
    """-> [n, dim] float32 unit vectors with intrinsic dimension basis.shape[0]."""
    out = np.empty((n, dim), np.float32)
    for lo in range(0, n, 100_000):
        z = rng.standard_normal((min(n, lo + 100_000) - lo, basis.shape[0]), dtype=np.float32)
        x = z @ basis + 0.05 * rng.standard_normal((len(z), dim), dtype=np.float32)
        out[lo : lo + len(z)] = x / np.linalg.norm(x, axis=1, keepdims=True)
    return out


class City:
    """A smooth random field R^2 -> R^dim over several length scales (random Fourier features:
    a street's look at 15 m, a block's at 150 m, a district's at 1.5 km) and session
    appearances."""

    SCALES = ((15.0, 0.6), (150.0, 0.3), (1500.0, 0.1))  # (length scale m, share of variance)

    def __init__(self, dim: int, km: float, rng: np.random.Generator, features: int = 512):
        self.size = km * 1000.0
        self.fields = [
            (
                rng.standard_normal((2, features)).astype(np.float32) / scale,
                rng.uniform(0, 2 * np.pi, features).astype(np.float32),
                rng.standard_normal((features, dim)).astype(np.float32)
                * np.sqrt(2.0 * share / features),
            )
            for scale, share in self.SCALES
        ]
        self.dim, self.rng = dim, rng

    def describe(self, xy: np.ndarray, session: np.ndarray) -> np.ndarray:
        """positions [n, 2] m, session appearance offsets [n, dim] -> unit descriptors [n, dim]:
        place signal of unit variance per dimension + session offset + per-frame noise."""
        xy = xy.astype(np.float32)
        x = sum(np.cos(xy @ omega + phase) @ mix for omega, phase, mix in self.fields)
        x += session + 0.3 * self.rng.standard_normal(x.shape, dtype=np.float32)
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    def appearance(self) -> np.ndarray:
        """A session's appearance offset (lighting, season): [dim], ~0.5 of the place signal."""
        return 0.5 * self.rng.standard_normal(self.dim).astype(np.float32)

    def drive(self, n: int) -> np.ndarray:
        """A smooth random walk of n keyframes 1 m apart inside the city -> [n, 2] m."""
        heading = np.cumsum(self.rng.normal(0.0, 0.05, n)) + self.rng.uniform(0, 2 * np.pi)
        steps = np.stack([np.cos(heading), np.sin(heading)], axis=1)
        xy = self.rng.uniform(0, self.size, 2) + np.cumsum(steps, axis=0)
        return np.abs((xy + self.size) % (2 * self.size) - self.size)  # reflect at the edges


def trajectory(n: int, dim: int, rng: np.random.Generator, km: float):
    """-> (descriptors [n, dim], positions [n, 2] m, the City): sessions of 10,000 keyframes."""
    city = City(dim, km, rng)
    out, xy_all = np.empty((n, dim), np.float32), np.empty((n, 2), np.float32)
    for lo in range(0, n, 10_000):
        hi = min(n, lo + 10_000)
        xy_all[lo:hi] = xy = city.drive(hi - lo)
        out[lo:hi] = city.describe(xy, city.appearance()[None])
    return out, xy_all, city


def trajectory_queries(city: City, xy: np.ndarray, limit: int, q: int, rng) -> np.ndarray:
    """Revisits of keyframes < `limit`: position moved up to 2 m, a new session's appearance."""
    picks = rng.integers(0, limit, q)
    moved = xy[picks] + rng.uniform(-2.0, 2.0, (q, 2)).astype(np.float32)
    return city.describe(moved, city.appearance()[None])


def time_searches(index: DescriptorIndex, queries: np.ndarray, k: int, max_id: int | None):
    """-> (ids [Q, k], latencies [Q] seconds), one query per call."""
    ids, lat = np.full((len(queries), k), -1, np.int64), np.empty(len(queries))
    for i, q in enumerate(queries):
        t0 = time.perf_counter()
        found, _ = index.search(q, k, max_id)
        lat[i] = time.perf_counter() - t0
        ids[i, : len(found)] = found
    return ids, lat


def build(descs: np.ndarray, config: IndexConfig, single_adds: int) -> tuple:
    """Index over descs (the last `single_adds` one at a time, as the live map adds) ->
    (index, build s, µs per single add)."""
    index, n = DescriptorIndex(descs.shape[1], config), len(descs)
    n_single = min(single_adds, n)
    t0 = time.perf_counter()
    for lo in tqdm(range(0, n - n_single, 50_000), desc=f"{config.kind} {n:.0e}", leave=False):
        index.add(descs[lo : min(lo + 50_000, n - n_single)])
    bulk = time.perf_counter() - t0
    t0 = time.perf_counter()
    for row in descs[n - n_single :]:
        index.add(row[None])
    single = (time.perf_counter() - t0) / max(n_single, 1)
    return index, bulk + single * n_single, single * 1e6


def bench_size(n, descs, queries, args) -> list[dict]:
    """Flat (exact) then one HNSW graph per M searched at every efSearch -> result rows."""
    flat, build_s, single = build(descs[:n], IndexConfig(kind="flat"), args.single_adds)
    exact, lat = time_searches(flat, queries, args.k, None)
    rows = [row(n, "flat", 0, 0, build_s, single, lat, 1.0, 1.0, flat)]
    del flat
    for m in args.hnsw_m if n <= args.hnsw_max else ():
        config = IndexConfig(kind="hnsw", hnsw_m=m, ef_construction=args.ef_construction,
                             ef_search=args.ef_search[0], exact_below=0)  # fmt: skip
        index, build_s, single = build(descs[:n], config, args.single_adds)
        for ef in args.ef_search:
            index.config = replace(config, ef_search=ef)
            ids, lat = time_searches(index, queries, args.k, None)
            hits = [len(set(a) & set(b)) for a, b in zip(ids, exact, strict=True)]
            recall, top1 = float(np.mean(hits)) / args.k, float(np.mean(ids[:, 0] == exact[:, 0]))
            rows.append(row(n, "hnsw", m, ef, build_s, single, lat, recall, top1, index))
        del index
    for nlist in args.ivf_nlist:
        rows += bench_ivf(descs[:n], queries, exact, nlist or int(np.sqrt(n)), args)
    return rows


def bench_ivf(descs, queries, exact, nlist: int, args) -> list[dict]:
    """FAISS IVF-Flat (k-means coarse quantizer, inner product) searched at every nprobe: not a
    place-map index (it needs training on the map's own descriptors), measured for comparison."""
    t0 = time.perf_counter()
    index = faiss.IndexIVFFlat(faiss.IndexFlatIP(descs.shape[1]), descs.shape[1], nlist,
                               faiss.METRIC_INNER_PRODUCT)  # fmt: skip
    index.cp.niter = 10  # k-means iterations (FAISS's default 25 triples the training time)
    sample = np.random.default_rng(args.seed).permutation(len(descs))[: 40 * nlist]
    index.train(descs[np.sort(sample)])
    index.add(descs)
    build_s, rows = time.perf_counter() - t0, []
    threads = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    for nprobe in args.nprobe:
        index.nprobe = nprobe
        ids, lat = np.full((len(queries), args.k), -1, np.int64), np.empty(len(queries))
        for i, q in enumerate(queries):
            t1 = time.perf_counter()
            ids[i] = index.search(q[None], args.k)[1][0]
            lat[i] = time.perf_counter() - t1
        hits = [len(set(a) & set(b)) for a, b in zip(ids, exact, strict=True)]
        recall, top1 = float(np.mean(hits)) / args.k, float(np.mean(ids[:, 0] == exact[:, 0]))
        size = faiss.serialize_index(index).nbytes / len(descs)
        rows.append(dict(n=len(descs), kind=f"ivf{nlist}", m="-", ef=nprobe, build=build_s,
                         single_us=float("nan"), med=np.median(lat) * 1e3,
                         p95=np.percentile(lat, 95) * 1e3, recall=recall, top1=top1,
                         bytes=size))  # fmt: skip
    faiss.omp_set_num_threads(threads)
    return rows


def row(n, kind, m, ef, build_s, single_us, lat, recall, top1, index) -> dict:
    size = faiss.serialize_index(index._index).nbytes / max(len(index), 1)
    return dict(n=n, kind=kind, m=m, ef=ef, build=build_s, single_us=single_us,
                med=np.median(lat) * 1e3, p95=np.percentile(lat, 95) * 1e3, recall=recall,
                top1=top1, bytes=size)  # fmt: skip


def print_rows(rows: list[dict], k: int, header: bool) -> None:
    if header:
        print(f"| keyframes | index | M | efSearch (IVF: nprobe) | build s | add µs (single) "
              f"| search ms median | p95 | recall@{k} | top-1 = exact "
              "| index B/keyframe |")  # fmt: skip
        print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        m, ef = (r["m"], r["ef"]) if r["kind"] != "flat" else ("-", "-")
        print(f"| {r['n']:.0e} | {r['kind']} | {m} | {ef} | {r['build']:.1f} | "
              f"{r['single_us']:.0f} | {r['med']:.3f} | {r['p95']:.3f} | {r['recall']:.3f} | "
              f"{r['top1']:.3f} | {r['bytes']:,.0f} |", flush=True)  # fmt: skip


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
    """Save a small map with full-size dense tokens; -> bytes per keyframe of each file."""
    rng = np.random.default_rng(args.seed + 1)
    n = args.mem_keyframes
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(dir=args.work_dir) as tmp:
        for kind in ("flat", "hnsw"):
            with PlaceMap(dim, shape, "bench", index=kind, work_dir=tmp) as m:
                descs = lowrank(n, dim, rng, rng.standard_normal((64, dim), np.float32))
                dense = rng.standard_normal(shape, dtype=np.float32)
                pose = (1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 1.0)
                for i in range(n):
                    meta = KeyframeMeta(stamp=1e9 + i, frame_id="camera", pose=pose, source="run1")
                    m.add(descs[i], dense + i, meta)
                d = Path(tmp) / f"map-{kind}"
                m.save(d)
            for f in os.listdir(d):
                role = f.split("-")[0] + ("_crc" if f.endswith(".crc") else "")
                if role in ("index", "meta", "dense", "dense_crc"):
                    key = f"{role}_{kind}" if role == "index" else role
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
    p.add_argument("--ivf-nlist", type=ints, default=[], help="IVF-Flat list counts to compare "
                   "(0: sqrt(n)); none by default")  # fmt: skip
    p.add_argument("--nprobe", type=ints, default=[16, 32, 64], help="IVF lists searched")
    p.add_argument("--single-adds", type=int, default=200, help="adds timed one at a time")
    p.add_argument("--city-km", type=float, default=5.0, help="trajectory data: city side, km")
    p.add_argument("--extrapolate", type=lambda v: int(float(v)), help="fit recall / time to "
                   "this size (e.g. 1e6) from the sizes run")  # fmt: skip
    p.add_argument("--threads", type=int, default=0, help="FAISS OpenMP threads for building")
    p.add_argument("--mem-keyframes", type=int, default=64, help="keyframes in the saved map")
    p.add_argument("--work-dir", default=None, help="folder for the saved test map")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    return p.parse_args(argv)


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
    print(f"\nBytes per keyframe (saved map of {args.mem_keyframes}, dense {shape} float16):\n")
    print("| file | bytes/keyframe |\n|---|---|")
    for key in ("dense", "dense_crc", "index_flat", "index_hnsw", "meta"):
        print(f"| {key} | {mem.get(key, 0):,.0f} |")
    total = mem["dense"] + mem["dense_crc"] + mem["meta"]
    print(f"| total (flat / hnsw M=32) | {total + mem['index_flat']:,.0f} / "
          f"{total + mem['index_hnsw']:,.0f} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
