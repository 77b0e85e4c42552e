"""Issue 34's lifelong run: one robot drives the demo world in 8 sessions, day and dusk light
alternating, each session replayed onto the map the sessions before it saved (load, map, save),
once with `map_growth` "places" (the default) and once with "all" (every keyframe stored).

The world is `generate_world(seed, laps=8)` (its lap offsets: every lap 1-3 m to the side and
10-25 deg off the first lap's heading); session k is lap k, a day after session k-1, rendered
with depth and the demo camera, posed by ground truth. Detector and geometry settings: the
demo's (config/demo.yaml: relative poses from depth, as `make demo`). Per session: map bytes
on disk after its save, keyframes stored (and of those, stored without features: another
keyframe lends them its features) and represented, and inter-session recall and
precision: a query keyframe is a positive when a frame of an earlier session lies within
`--gt-radius` of it (every frame driven, stored or represented: every place must stay
findable), an accepted loop is true when its match lies within `--gt-radius` of the query.

    nice -n 10 python benchmarks/bench_lifelong.py --frames 100 --out /var/tmp/lifelong \
        --png docs/img/lifelong-map-size.png
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np

from pair_vpr_ros.demo.camera import Camera
from pair_vpr_ros.demo.layout import DAY, DUSK
from pair_vpr_ros.demo.views import camera_model, render_keyframe
from pair_vpr_ros.demo.world import World, generate_world
from pair_vpr_ros.identity import Identity
from pair_vpr_ros.loops.frames import Frame, FrameOutcome
from pair_vpr_ros.loops.growth import MapGrowth
from pair_vpr_ros.loops.pipeline import LoopClosurePipeline
from pair_vpr_ros.params.configs import detector_config, geometry_config
from pair_vpr_ros.params.file import read_params_file
from pair_vpr_ros.place_map import PlaceMap
from pair_vpr_ros.place_map.growth.policy import GrowthConfig
from pair_vpr_ros.weights import load_model

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "pair_vpr_ros/demo/assets/demo-small.pth"
DAY_S = 86_400.0
POLICIES = ("places", "all")


def session_frames(world: World, k: int) -> list[Frame]:
    """Lap k of the world as the frames of session k (stamps k days later), with depth, the
    demo camera's intrinsics and the ground-truth pose (x, y, 0, yaw as a quaternion)."""
    cam = camera_model(Camera(width=world.config.width, height=world.config.height))
    out = []
    for i in np.flatnonzero(world.lap == k):
        rgb, depth = render_keyframe(world, int(i))
        x, y, yaw = (float(v) for v in world.poses[i][:3])
        pose = (x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        stamp = float(world.stamps[i]) + k * DAY_S
        out.append(Frame(stamp, rgb, "camera", pose, depth=depth, camera=cam))
    return out


def map_bytes(directory: Path) -> int:
    files = (p for p in directory.iterdir() if p.is_file() and p.name != "map.lock")
    return sum(p.stat().st_size for p in files)


def score(outcomes: list[FrameOutcome], place_map: PlaceMap, earlier: np.ndarray, radius: float,
          frames: list[Frame]) -> dict:  # fmt: skip
    """Inter-session recall and precision of one session's outcomes (module docstring)."""
    by_stamp = {f.stamp: np.asarray(f.pose[:2]) for f in frames}
    positives = found = true = false = 0
    for out in outcomes:
        if out.skipped:
            continue
        here = by_stamp[out.stamp]
        positive = bool(len(earlier)) and bool(np.min(np.hypot(*(earlier - here).T)) <= radius)
        positives += positive
        for loop in (r for r in out.decisions() if r.accepted):  # one map: at most one
            match = np.asarray(place_map.meta(loop.match_id).pose[:2])
            ok = bool(np.hypot(*(match - here)) <= radius)
            true, false, found = true + ok, false + (not ok), found + (ok and positive)
    return {
        "positives": positives,
        "true_loops": true,
        "false_loops": false,
        "recall": found / positives if positives else None,
        "precision": true / (true + false) if true + false else None,
    }


def run(args: argparse.Namespace) -> dict:
    values = read_params_file(ROOT / "config/demo.yaml")
    model = load_model(WEIGHTS)
    world = generate_world(args.seed, frames=8 * args.frames, laps=8)
    world = dataclasses.replace(world, lightings=(DAY, DUSK) * 4)
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    results: dict[str, list] = {p: [] for p in args.policies}
    growth = GrowthConfig(max_translation_m=args.max_translation_m,
                          max_rotation_deg=args.max_rotation_deg)  # fmt: skip
    earlier = np.zeros((0, 2))
    for k in range(8):
        t0 = time.perf_counter()
        frames = session_frames(world, k)
        render_s = time.perf_counter() - t0
        for policy in args.policies:
            t1 = time.perf_counter()
            directory = out / policy
            config = detector_config(values).updated(map_growth=policy)
            who = Identity("robot", f"day{k + 1}")
            place_map = PlaceMap.load(directory, model.fingerprint) if k else None
            pipe = LoopClosurePipeline(model, config, place_map=place_map,
                                       geometry=geometry_config(values), identity=who)  # fmt: skip
            pipe.growth = MapGrowth(growth)
            outcomes = list(pipe.process_many(frames, batch_size=8))
            pipe.save_map(directory)
            m = pipe.place_map
            counts = m.growth.counts()
            sessions = score(outcomes, m, earlier, args.gt_radius, frames)
            stored = len(m)
            shared = sum(not m.features(i) for i in range(stored))
            pipe.close()  # folds the WAL into the store: the bytes a robot keeps
            row = {
                "session": k + 1, "lighting": world.lightings[k].name,
                "hours": (k + 1) * len(frames) / world.config.rate_hz / 3600.0,
                "map_bytes": map_bytes(directory), "stored": stored, "lent_features": shared,
                "represented": counts.represented, "links": counts.links,
                "session_stored": sum(o.keyframe_id is not None for o in outcomes),
                "session_represented": pipe.counts.represented,
                **sessions,
                "seconds": round(time.perf_counter() - t1 + render_s / 2, 1),
            }  # fmt: skip
            results[policy].append(row)
            print(json.dumps({"policy": policy, **row}), flush=True)
        earlier = np.concatenate([earlier, [f.pose[:2] for f in frames]])
    return results


def plot(results: dict, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for policy, rows in results.items():
        hours = [0.0] + [r["hours"] * 60 for r in rows]
        size = [0.0] + [r["map_bytes"] / 1e6 for r in rows]
        ax.plot(hours, size, marker="o", label=f"map_growth: {policy}")
    ax.set_xlabel("minutes driven (8 sessions, day / dusk alternating)")
    ax.set_ylabel("map on disk (MB)")
    ax.set_title("Lifelong run on the demo world")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=100, help="frames per session (one lap)")
    p.add_argument("--seed", type=int, default=7, help="demo world seed (7: make demo's)")
    p.add_argument("--gt-radius", type=float, default=10.0, help="m, as the replay's default")
    p.add_argument("--out", default="/var/tmp/pairvpr-lifelong", help="folder of the two maps")
    p.add_argument("--policies", nargs="+", choices=POLICIES, default=list(POLICIES))
    defaults = GrowthConfig()
    p.add_argument("--max-translation-m", type=float, default=defaults.max_translation_m)
    p.add_argument("--max-rotation-deg", type=float, default=defaults.max_rotation_deg)
    p.add_argument("--png", type=Path, help="write the map size against time driven here")
    p.add_argument("--json", type=Path, help="write every row here")
    args = p.parse_args()
    t0 = time.perf_counter()
    results = run(args)
    for policy, rows in results.items():
        ratio = rows[-1]["map_bytes"] / rows[0]["map_bytes"]
        recall2 = rows[1]["recall"]
        worst = min(r["recall"] for r in rows[1:])
        precision = min(r["precision"] for r in rows[1:])
        print(
            f"{policy}: bytes after 8 sessions / after 1 = {ratio:.2f} (target <= 2.5: "
            f"{'met' if ratio <= 2.5 else 'not met'}); inter-session recall of session 2 "
            f"{recall2:.3f}, lowest {worst:.3f} (target >= {recall2 - 0.02:.3f}: "
            f"{'met' if worst >= recall2 - 0.02 else 'not met'}); lowest precision "
            f"{precision:.3f} (target >= 0.95: {'met' if precision >= 0.95 else 'not met'})"
        )
    print(f"total {time.perf_counter() - t0:.0f} s")
    if args.png:
        plot(results, args.png)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
