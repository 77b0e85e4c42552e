"""How the cost of a saved place map grows with its size (issue 34): ViT-B/322-shaped keyframes.

For each size N (default 1k, 5k, 20k keyframes), three child processes (so peak RSS and timings
belong to one phase each):

1. build: N keyframes (random [512] descriptors, [529, 768] tokens and SIFT features of 1000
   keypoints with depth, packed as the default settings store them: compact, 500 kept), one save.
2. grow: load the map, add 100 keyframes, save (an incremental save); bytes written (`wchar` of
   /proc/self/io: every write call, page cache included) by the adds + the save and by the save
   alone, against the bytes those 100 keyframes add to the folder.
3. query: load (timed: median and fastest of 5 loads in the process), one search (timed: the
   first checks and touches every descriptor), 20 queries:
   search top-5, their dense tokens, metadata and the best match's features; bytes read per
   query (`rchar`) and the process's peak RSS.

    python benchmarks/bench_map_growth.py --sizes 1000,5000 --work-dir /var/tmp
    python benchmarks/bench_map_growth.py --codec f16   # the uncompressed form

Timings are ratios to the smallest size within one run (the page cache is warm: the map was
just written). Targets (issue 34): written by a save after +100 <= 1.5 x their bytes + 1 MB;
save at 20k <= 1.5 x at 1k; load at 20k <= 3 x at 1k; dense tokens <= 200 KiB and disk
<= 250 KB per keyframe.
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pair_vpr_ros.geometry.features import Features, pack_features
from pair_vpr_ros.place_map import IndexConfig, KeyframeMeta, PlaceMap
from pair_vpr_ros.place_map.dense_codec import CODECS, DEFAULT_CODEC

DIM, SHAPE, ADD, QUERIES, LOADS = 512, (529, 768), 100, 20, 5


def io_counters() -> dict[str, int]:
    with open("/proc/self/io") as fh:
        return {k: int(v) for k, v in (line.split(": ") for line in fh)}


class Keyframes:
    """Random keyframes of the real shapes (a small pool of tokens and features, reused)."""

    def __init__(self, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.rng = rng
        self.tokens = [rng.standard_normal(SHAPE, np.float32).astype(np.float16) for _ in range(8)]
        self.features = [self._features(rng) for _ in range(8)]

    @staticmethod
    def _features(rng: np.random.Generator, n: int = 1000) -> bytes:
        kp = rng.uniform(0, 640, (n, 2)).astype(np.float32)
        desc = rng.integers(0, 256, (n, 128), dtype=np.uint8)
        return pack_features(Features(kp, desc, "sift", rng.uniform(1, 9, n).astype(np.float32)))

    def add(self, m: PlaceMap, count: int) -> None:
        for _ in range(count):
            i = len(m)
            pose = (float(i), 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
            meta = KeyframeMeta(stamp=1e9 + i, frame_id="camera", pose=pose, source="bench")
            desc = self.rng.standard_normal(DIM, np.float32)
            m.add(desc, self.tokens[i % 8], meta, self.features[i % 8])


def folder_bytes(d: Path) -> int:
    return sum(p.stat().st_size for p in d.iterdir() if p.is_file() and p.name != "map.lock")


def phase_build(d: Path, n: int, codec: str) -> dict:
    kf = Keyframes(n)
    t0 = time.perf_counter()
    with PlaceMap(DIM, SHAPE, "bench", IndexConfig(dense_codec=codec), work_dir=d.parent) as m:
        kf.add(m, n)
        t1 = time.perf_counter()
        m.save(d)
        t2 = time.perf_counter()
        dense = m.bytes_per_keyframe - 4 * DIM
    return {"build_s": t1 - t0, "first_save_s": t2 - t1, "disk_bytes": folder_bytes(d),
            "dense_bytes_per_keyframe": dense}  # fmt: skip


def phase_grow(d: Path, n: int, codec: str) -> dict:
    kf = Keyframes(n + 1)
    before = folder_bytes(d)
    with PlaceMap.load(d) as m:
        io0 = io_counters()
        kf.add(m, ADD)
        io1 = io_counters()
        t0 = time.perf_counter()
        m.flush()  # as vpr_node saves: fsync off the map thread,
        t1 = time.perf_counter()
        m.save(d, checkpoint=False)  # commit on it (the keyframes' stall),
        t2 = time.perf_counter()
        m.checkpoint()  # WAL folded in off it
        t3 = time.perf_counter()
        io2 = io_counters()
    added = folder_bytes(d) - before  # what the 100 keyframes take on disk (the WAL folded in)
    return {"save_add_s": t3 - t0, "save_stall_s": t2 - t1, "added_bytes": added,
            "written_by_adds_and_save": io2["wchar"] - io0["wchar"],
            "written_by_save": io2["wchar"] - io1["wchar"]}  # fmt: skip


def phase_query(d: Path, n: int, codec: str) -> dict:
    rng = np.random.default_rng(7)
    loads = []
    for _ in range(LOADS):  # on 2 busy cores one load's time is mostly the scheduler's
        t0 = time.perf_counter()
        m = PlaceMap.load(d, read_only=True, dense_cache_size=0)
        loads.append(time.perf_counter() - t0)
        if len(loads) < LOADS:
            m.close()
    load_s, load_min_s = float(np.median(loads)), min(loads)
    io0 = io_counters()
    t0 = time.perf_counter()
    m.search(rng.standard_normal(DIM, np.float32), 5)  # touches every descriptor once
    first_search_s = time.perf_counter() - t0
    for _ in range(QUERIES):
        hits = m.search(rng.standard_normal(DIM, np.float32), 5)
        ids = [i for i, _ in hits]
        m.get_dense(ids)
        for i in ids:
            m.meta(i)
        m.features(ids[0])
    io1 = io_counters()
    m.close()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"load_s": load_s, "load_min_s": load_min_s, "first_search_s": first_search_s,
            "read_per_query": (io1["rchar"] - io0["rchar"]) / QUERIES,
            "peak_rss": rss}  # fmt: skip


PHASES = {"build": phase_build, "grow": phase_grow, "query": phase_query}


def run_size(n: int, codec: str, work: Path) -> dict:
    d = work / f"map-{n}"
    out = {"keyframes": n}
    for phase in PHASES:
        cmd = [sys.executable, __file__, "--phase", phase, "--dir", str(d), "--n", str(n),
               "--codec", codec]  # fmt: skip
        done = subprocess.run(cmd, check=True, capture_output=True, text=True)
        out.update(json.loads(done.stdout.splitlines()[-1]))
    out["disk_per_keyframe"] = out["disk_bytes"] / n
    shutil.rmtree(d)
    return out


def report(rows: list[dict]) -> None:
    base = rows[0]
    print(
        "| keyframes | disk / keyframe | dense / keyframe | +100: written (adds + save) / "
        "their bytes | written by the save | save | of it on the map thread | load (fastest) | "
        "first search | read / query | peak RSS |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ratio = r["written_by_adds_and_save"] / r["added_bytes"]
        print(
            f"| {r['keyframes']:,} | {r['disk_per_keyframe'] / 1e3:.0f} KB | "
            f"{r['dense_bytes_per_keyframe'] / 1024:.1f} KiB | "
            f"{r['written_by_adds_and_save'] / 1e6:.1f} MB / {r['added_bytes'] / 1e6:.1f} MB "
            f"({ratio:.2f}x) | {r['written_by_save'] / 1e6:.2f} MB | "
            f"{r['save_add_s'] * 1e3:.0f} ms ({r['save_add_s'] / base['save_add_s']:.2f}x) | "
            f"{r['save_stall_s'] * 1e3:.0f} ms | "
            f"{r['load_s'] * 1e3:.1f} ms ({r['load_s'] / base['load_s']:.2f}x; "
            f"{r['load_min_s'] * 1e3:.1f} ms, {r['load_min_s'] / base['load_min_s']:.2f}x) | "
            f"{r['first_search_s'] * 1e3:.0f} ms | "
            f"{r['read_per_query'] / 1e6:.2f} MB | {r['peak_rss'] / 2**20:.0f} MiB |"
        )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="1000,5000,20000", help="keyframe counts (comma list)")
    p.add_argument("--codec", default=DEFAULT_CODEC, choices=CODECS, help="dense_codec")
    p.add_argument("--work-dir", default=None, help="where the maps are written (then deleted)")
    p.add_argument("--json", default=None, help="also write the figures to this file")
    p.add_argument("--phase", choices=list(PHASES), help=argparse.SUPPRESS)
    p.add_argument("--dir", help=argparse.SUPPRESS)
    p.add_argument("--n", type=int, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.phase:
        print(json.dumps(PHASES[args.phase](Path(args.dir), args.n, args.codec)))
        return 0
    rows = []
    work = work_folder(p, args.work_dir)
    with tempfile.TemporaryDirectory(prefix="bench-growth-", dir=work) as tmp:
        for n in (int(v) for v in args.sizes.split(",")):
            rows.append(run_size(n, args.codec, Path(tmp)))
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    report(rows)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 0


def work_folder(parser: argparse.ArgumentParser, path: str | None) -> str | None:
    """`--work-dir`, made when missing (parents too); a path that cannot be a folder exits with
    parser.error (status 2) saying why."""
    if path is None:
        return None
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError as err:
        parser.error(f"--work-dir {path}: cannot make this folder ({err.strerror}); pass a folder "
                     "on a disk with room for the maps")  # fmt: skip
    return path


if __name__ == "__main__":
    sys.exit(main())
