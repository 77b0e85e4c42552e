"""Keyframe latency of the node's map thread with and without autosave (issue 34).

`vpr_node` runs every frame through `MapControl.process` on its map thread, and its autosave
timer calls `MapControl.autosave` from another thread: the dense tokens are fsynced off the map
thread, the new rows are committed on it, and the WAL is folded in off it. This benchmark drives
that same `MapControl` and `LoopClosurePipeline` over a saved map of ViT-B/322-shaped keyframes
(random descriptors and tokens, `bench_map_growth.Keyframes`), with the network replaced by
random outputs of its shapes: what is timed is everything but the network (map search, the
dense-token reads of the re-ranking, the add, the saves), so the ratio is a strict bound on the
node's (a real ViT-B adds the same encode time to both runs).

A camera thread sends a frame every `--period-ms` for `--seconds`; each frame's latency is from
its send to its outcome. The run with autosave saves every `--autosave-s` seconds (the
`autosave_period` parameter); the run without saves once at its end (the node's
save_on_shutdown). Prints p50 / p95 / max of both runs and p95 with / without (issue 34's
target: <= 1.2 at >= 5k keyframes), and the disk the open map takes (issue 48): the store's
write-ahead log (`-wal`) at its largest and at the end, and the folder's bytes per keyframe
open (with the -wal) and closed (folded in).

    python benchmarks/bench_autosave_latency.py --keyframes 5000 --work-dir /var/tmp/bench
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from bench_map_growth import DIM, SHAPE, Keyframes, folder_bytes, work_folder

from pair_vpr_ros.geometry.features import unpack_features
from pair_vpr_ros.geometry.keyframes import GeometryConfig
from pair_vpr_ros.loops.detector import DetectorConfig
from pair_vpr_ros.loops.frames import Frame
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.place_map import IndexConfig, PlaceMap
from pair_vpr_ros.ros.maps import MapControl

FINGERPRINT = "bench"


class ShapedPipeline(LoopClosurePipeline):
    """The pipeline with the network's outputs drawn at random (its shapes, no compute); the
    re-ranking still reads its candidates' dense tokens from the map."""

    def encode(self, images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        rng = np.random.default_rng()
        desc = rng.standard_normal((len(images), DIM), np.float32)
        desc /= np.linalg.norm(desc, axis=1, keepdims=True)
        dense = rng.standard_normal((len(images), *SHAPE), np.float32).astype(np.float16)
        return dense, desc

    def pair_scores(self, dense: np.ndarray, ids: list[int]) -> np.ndarray:
        tokens = self.place_map.get_dense(ids)  # the I/O of a real re-ranking
        return np.full(len(tokens), -10.0, np.float32)  # below any threshold: no loop


def fake_model() -> SimpleNamespace:
    config = SimpleNamespace(desc_dim=DIM, embed_dim=SHAPE[1], image_size=(322, 322))
    return SimpleNamespace(fingerprint=FINGERPRINT, config=config, num_patches=SHAPE[0],
                           device="cpu", dense_dtype=torch.float16)  # fmt: skip


def build(d: Path, n: int) -> None:
    if (d / "manifest.json").exists():
        return
    with PlaceMap(DIM, SHAPE, FINGERPRINT, IndexConfig(), work_dir=d.parent) as m:
        Keyframes(n).add(m, n)
        m.save(d)


def shaped(features: bool) -> ShapedPipeline:
    """The pipeline of a run; `features`: each keyframe stores 1000 SIFT keypoints with depth
    (`Keyframes`' packed form, as a node with relative poses stores), not extracted."""
    config = DetectorConfig(exclude_recent_s=0.0)  # top_k 10, as the node
    pipe = ShapedPipeline(fake_model(), config, geometry=GeometryConfig(relative_pose=False))
    if features:
        stored = unpack_features(Keyframes(0).features[0])
        pipe.geometry.wanted = lambda verification: True
        pipe.geometry.extract = lambda *args, **kwargs: stored
    return pipe


def run(d: Path, seconds: float, period_s: float, autosave_s: float, features: bool) -> dict:
    """Frames through MapControl for `seconds` -> latency figures (ms) and saves done."""
    maps = MapControl(lambda: shaped(features),
                      lambda level, text: print(f"[{level}] {text}", file=sys.stderr))  # fmt: skip
    ok, text = maps.load(str(d))
    assert ok, text
    stop, saves = threading.Event(), []

    def autosave() -> None:
        while not stop.wait(autosave_s):
            t0 = time.perf_counter()
            result = maps.autosave(str(d))
            if result is not None:
                saves.append(time.perf_counter() - t0)

    saver = threading.Thread(target=autosave, daemon=True)
    if autosave_s > 0:
        saver.start()
    rgb, latency, wal = np.zeros((32, 32, 3), np.uint8), [], [0]
    start = time.perf_counter()
    for i in range(int(seconds / period_s)):
        due = start + i * period_s
        time.sleep(max(0.0, due - time.perf_counter()))
        sent = time.perf_counter()
        maps.process(Frame(stamp=2e9 + i * period_s, rgb=rgb))
        latency.append(time.perf_counter() - sent)
        wal.append(wal_bytes(d))
    stop.set()
    if saver.is_alive():
        saver.join()
    if autosave_s <= 0:
        maps.save(str(d))  # save_on_shutdown
    keyframes = maps.size()
    wal.append(wal_bytes(d))
    open_bytes = folder_bytes(d)
    maps.close()
    ms = np.array(latency) * 1e3
    return {"frames": len(ms), "p50_ms": float(np.percentile(ms, 50)),
            "p95_ms": float(np.percentile(ms, 95)), "max_ms": float(ms.max()),
            "saves": len(saves), "save_s": [round(s, 2) for s in saves],
            "keyframes": keyframes, "wal_max_mb": max(wal) / 1e6, "wal_end_mb": wal[-1] / 1e6,
            "open_kb_per_keyframe": open_bytes / keyframes / 1e3,
            "closed_kb_per_keyframe": folder_bytes(d) / keyframes / 1e3}  # fmt: skip


def wal_bytes(d: Path) -> int:
    """Bytes of the store's -wal (0 while there is none)."""
    try:
        return sum(p.stat().st_size for p in d.glob("map-*.sqlite-wal"))
    except FileNotFoundError:  # folded in and removed meanwhile
        return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--keyframes", type=int, default=5000, help="keyframes in the map")
    parser.add_argument("--seconds", type=float, default=60.0, help="length of each run")
    parser.add_argument("--period-ms", type=float, default=200.0, help="one frame every this")
    parser.add_argument("--autosave-s", type=float, default=10.0, help="autosave_period")
    parser.add_argument("--work-dir", type=Path, default=None,
                        help="where the map is built (default: a temporary folder)")  # fmt: skip
    parser.add_argument("--features", action="store_true",
                        help="new keyframes store SIFT features too (~36 KB each, as with "
                        "relative poses); default: none, as issue 34's runs")  # fmt: skip
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(dir=work_folder(parser, args.work_dir)) as tmp:
        d = Path(tmp) / "map"
        t0 = time.perf_counter()
        build(d, args.keyframes)
        print(f"built {args.keyframes} keyframes in {time.perf_counter() - t0:.0f} s")
        rows = {}
        for name, autosave_s in (("no autosave", 0.0), ("autosave", args.autosave_s)):
            rows[name] = run(d, args.seconds, args.period_ms / 1e3, autosave_s, args.features)
            print(name, json.dumps(rows[name]))
        ratio = rows["autosave"]["p95_ms"] / rows["no autosave"]["p95_ms"]
        print(f"p95 with / without autosave: {ratio:.2f} (target <= 1.2)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
