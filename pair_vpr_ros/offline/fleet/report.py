"""`python -m pair_vpr_ros.offline.fleet.report FLEET_DIR`: the demo fleet's figures.

Reads what ``scripts/demo_fleet.sh`` wrote into ``FLEET_DIR``: ``fleet.json`` and the bags
(ground truth), each drive's replay (``replay/<robot>_<session>/loops.json``, replayed in the
order of ``fleet.json``, each with the earlier drives' maps as prior maps), the fleet exchange
(``exchange/``) and the pose graph
(``posegraph/posegraph.json``), and writes ``summary.json``:

``inter_robot`` / ``inter_session``
    accepted loops between two robots / two sessions of one robot: ``true`` and ``false``
    (a loop is true when its two keyframes' ground-truth positions lie within ``radius_m``),
    ``precision``; ``possible``: query keyframes with a keyframe of such a prior drive within
    ``radius_m``; ``recall``: those with an accepted true loop of the kind / ``possible``.
``relocalisation``
    per later session of a robot: keyframes (replay records, in stamp order) until its first
    accepted true loop into an earlier session of the robot (the first one counted:
    ``keyframes_until_relocalised``) and into any earlier drive (``keyframes_until_in_the_map``).
``trajectories``, ``all_in_one_frame``
    per robot-session ATE (SE(3)-aligned) of odometry and optimised trajectory, their ratio, and
    the ATE after the first robot's alignment only; all in one frame when each is within 1 m.
``exchange``, ``bytes_per_keyframe``, ``bytes_per_accepted_loop``
    the first sessions' fleet exchange (``exchange/``, ``pairvpr-fleet-replay``; null without
    one): its accepted loops judged alone (``true``, ``false``, ``precision``), how many were
    ``added_to_graph`` (a pair no replay accepted: ``offline.fleet.loops``) and
    ``found_by_a_replay_too``,
    its bytes (``bytes_sent`` by channel); bytes per own keyframe of ``descriptors`` and of
    ``all`` fleet messages, bytes per accepted inter-robot loop of ``scoring`` (requests and
    responses) and of ``all``. The added loops count in ``inter_robot`` / ``inter_session``
    (each keyframe pair once); recall counts distinct query keyframes.
``targets``: issue 22's targets, each with the figure and whether it is met.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from pair_vpr_ros.cli import run_cli
from pair_vpr_ros.errors import PoseGraphError
from pair_vpr_ros.offline.bags.opening import open_bag
from pair_vpr_ros.offline.fleet.loops import EXCHANGE, exchange_loops, read_drives, replay_records
from pair_vpr_ros.offline.posegraph.single import PoseGraphSummary, read_track

KINDS = ("inter_robot", "inter_session", "intra")


def _ground_truth(fleet: Path, drives: list[dict]) -> dict[tuple[str, str], Any]:
    out = {}
    for d in drives:
        with open_bag(fleet / d["bag"]) as reader:
            out[(d["robot"], d["session"])] = read_track(
                reader, "/ground_truth", "ground-truth", PoseGraphSummary()
            )
    return out


def _position(truth: Any, stamp: float) -> np.ndarray:
    i = int(np.clip(np.searchsorted(truth.stamps, stamp), 1, len(truth.stamps) - 1))
    j = i if abs(truth.stamps[i] - stamp) < abs(truth.stamps[i - 1] - stamp) else i - 1
    return truth.poses[j, :2]


def _kind(query: tuple[str, str], match: tuple[str, str]) -> str:
    if query[0] != match[0]:
        return "inter_robot"
    return "inter_session" if query[1] != match[1] else "intra"


class _Judge:
    """Counts accepted loops by kind, true (both ends within ``radius_m``) or false, and the
    query keyframes with a true loop of each kind."""

    def __init__(self, truth: dict, radius_m: float) -> None:
        self.truth, self.radius_m = truth, radius_m
        self.kinds = {k: {"true": 0, "false": 0} for k in KINDS}
        self.found: dict[str, set] = {k: set() for k in KINDS}

    def __call__(self, me: tuple[str, str], record: dict) -> tuple[str, bool] | None:
        """(kind, true) of an accepted loop queried by `me`, counted; None: unknown match."""
        other = (record.get("match_robot") or me[0], record.get("match_session") or me[1])
        if other not in self.truth or me not in self.truth:
            return None
        at = _position(self.truth[me], record["query_stamp"])
        there = _position(self.truth[other], record["match_stamp"])
        kind, true = _kind(me, other), bool(np.linalg.norm(there - at) <= self.radius_m)
        self.kinds[kind]["true" if true else "false"] += 1
        if true:
            self.found[kind].add((*me, round(float(record["query_stamp"]), 6)))
        return kind, true


def _query(record: dict) -> tuple[str, str]:
    return record["query_robot"], record["query_session"]


def loop_figures(fleet: Path, radius_m: float = 10.0) -> dict[str, Any]:
    """Loop counts by kind (the replays' loops and the exchange's added ones), recall
    denominators, relocalisation and the exchange's own counts (see module docstring)."""
    drives = read_drives(fleet)
    truth = _ground_truth(fleet, drives)
    ids = [(d["robot"], d["session"]) for d in drives]
    judge = _Judge(truth, radius_m)
    possible: dict[str, set] = {k: set() for k in KINDS}
    relocalisation, identities = {}, 0
    for n, drive in enumerate(drives):
        me, priors = ids[n], ids[:n]
        first_session = next(i for i in ids if i[0] == me[0])
        reloc = in_map = None
        queried: set[float] = set()  # keyframes so far (a keyframe may have a loop per map)
        for record in replay_records(fleet, drive):
            queried.add(record["query_stamp"])
            k = len(queried)
            at = _position(truth[me], record["query_stamp"])
            for kind in ("inter_robot", "inter_session"):
                near = [p for p in priors if _kind(me, p) == kind and np.min(np.linalg.norm(
                    truth[p].poses[:, :2] - at, axis=1)) <= radius_m]  # fmt: skip
                if near:
                    possible[kind].add((*me, round(float(record["query_stamp"]), 6)))
            if not record.get("accepted"):
                continue
            identities += bool(record.get("match_robot"))
            judged = judge(me, record)
            if judged is None:
                continue
            if reloc is None and judged == ("inter_session", True):
                reloc = k
            if in_map is None and judged[1] and judged[0] != "intra":
                in_map = k
        if me != first_session:
            relocalisation[f"{me[0]}/{me[1]}"] = {
                "keyframes_until_relocalised": reloc, "keyframes_until_in_the_map": in_map
            }  # fmt: skip
    exchange = _exchange_counts(fleet, truth, radius_m, judge)
    kinds = {}
    for kind, counts in judge.kinds.items():
        accepted, found = counts["true"] + counts["false"], judge.found[kind] & possible[kind]
        kinds[kind] = {
            **counts, "possible": len(possible[kind]),
            "precision": counts["true"] / accepted if accepted else None,
            "recall": len(found) / len(possible[kind]) if possible[kind] else None,
        }  # fmt: skip
    return {**kinds, "relocalisation": relocalisation, "loops_naming_robots": identities,
            "exchange": exchange, "radius_m": radius_m}  # fmt: skip


def _exchange_counts(fleet: Path, truth: dict, radius_m: float, judge: _Judge) -> dict | None:
    """The exchange's accepted loops judged on their own; the added ones also by `judge`."""
    loops = exchange_loops(fleet)
    if loops is None:
        return None
    accepted, added = loops
    alone = _Judge(truth, radius_m)
    for record in accepted:
        alone(_query(record), record)
    for record in added:
        judge(_query(record), record)
    true = sum(c["true"] for c in alone.kinds.values())
    false = sum(c["false"] for c in alone.kinds.values())
    return {"accepted": len(accepted), "true": true, "false": false,
            "precision": true / (true + false) if true + false else None,
            "added_to_graph": len(added), "found_by_a_replay_too": len(accepted) - len(added),
            **_exchange_bytes(fleet)}  # fmt: skip


def _exchange_bytes(fleet: Path) -> dict[str, Any]:
    path = fleet / EXCHANGE / "fleet_summary.json"
    if not path.is_file():
        raise PoseGraphError(f"fleet exchange without its summary: {path} missing")
    t = json.loads(path.read_text())["totals"]
    loops = t["inter_robot_loops"]
    return {
        "keyframes": t["keyframes"], "bytes_sent": t["bytes_sent"],
        "descriptor_bytes_per_keyframe": t["descriptor_bytes_per_keyframe"],
        "bytes_per_keyframe": t["bytes_per_keyframe"],
        "scoring_bytes_per_accepted_loop": t["scoring_bytes_per_accepted_loop"],
        "bytes_per_accepted_loop": sum(t["bytes_sent"].values()) / loops if loops else None,
    }  # fmt: skip


def trajectory_figures(posegraph_json: Path) -> dict[str, Any]:
    """Per robot-session ATE before / after / in the first one's frame, from posegraph.json."""
    data = json.loads(posegraph_json.read_text())
    out = {}
    for name, item in data["trajectories"].items():
        errors = item.get("errors", {})
        before = errors.get("odometry", {}).get("ate_rmse")
        after = errors.get("optimised", {}).get("ate_rmse")
        out[name] = {
            "joined": item["joined"], "ate_odometry_m": before, "ate_optimised_m": after,
            "ratio": after / before if before and after is not None else None,
            "ate_in_reference_frame_m": errors.get("ate_in_reference_frame"),
            "loops_within": item["loops_within"], "loops_between": item["loops_between"],
        }  # fmt: skip
    return out


def _targets(loops: dict, trajs: dict) -> dict[str, Any]:
    robot, reloc, ex = loops["inter_robot"], loops["relocalisation"], loops["exchange"]
    worst = [t["ate_in_reference_frame_m"] for t in trajs.values()]
    ratios = [t["ratio"] for t in trajs.values()]
    after = [t["ate_optimised_m"] for t in trajs.values()]
    first = [r["keyframes_until_relocalised"] for r in reloc.values()]

    def met(values: list, test: Any) -> bool:
        return bool(values) and all(v is not None and test(v) for v in values)

    return {
        "inter_robot_precision>=0.95": met([robot["precision"]], lambda v: v >= 0.95),
        "inter_robot_recall>=0.8": met([robot["recall"]], lambda v: v >= 0.8),
        "relocalised_within_5_keyframes": met(first, lambda v: v <= 5),
        "ate_ratio<=0.2": met(ratios, lambda v: v <= 0.2),
        "ate<=0.5m": met(after, lambda v: v <= 0.5),
        "all_in_one_frame_within_1m": met(worst, lambda v: v <= 1.0),
        "descriptor_bytes_per_keyframe<=1536": met(
            [ex and ex["descriptor_bytes_per_keyframe"]], lambda v: v <= 1536
        ),
    }


def fleet_summary(fleet: str | Path, radius_m: float = 10.0) -> dict[str, Any]:
    """``summary.json``'s content for the fleet folder ``fleet``."""
    fleet = Path(fleet)
    loops = loop_figures(fleet, radius_m)
    trajs = trajectory_figures(fleet / "posegraph" / "posegraph.json")
    in_frame = [t["ate_in_reference_frame_m"] for t in trajs.values()]
    notes, ex = [], loops["exchange"]
    if ex is None:
        notes.append("no fleet exchange (exchange/inter_robot_loops.json): bytes not measured")
    if not loops["loops_naming_robots"]:
        notes.append(
            "no accepted loop names another robot or session: the replay does not "
            "take --robot-id / --prior-map yet, so only loops within a drive exist"
        )
    return {
        "inter_robot": loops["inter_robot"], "inter_session": loops["inter_session"],
        "intra": loops["intra"], "relocalisation": loops["relocalisation"],
        "radius_m": radius_m, "trajectories": trajs,
        "all_in_one_frame": bool(in_frame) and all(v is not None and v <= 1.0 for v in in_frame),
        "exchange": ex,
        "bytes_per_keyframe": ex and {"descriptors": ex["descriptor_bytes_per_keyframe"],
                                      "all": ex["bytes_per_keyframe"]},
        "bytes_per_accepted_loop": ex and {"scoring": ex["scoring_bytes_per_accepted_loop"],
                                           "all": ex["bytes_per_accepted_loop"]},
        "targets": _targets(loops, trajs), "notes": notes,
        "png": str(fleet / "posegraph" / "posegraph.png"),
    }  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m pair_vpr_ros.offline.fleet.report",
        description="the demo fleet's figures -> FLEET/summary.json",
    )
    p.add_argument("fleet", type=Path, help="folder scripts/demo_fleet.sh wrote (fleet.json)")
    p.add_argument(
        "--radius",
        type=float,
        default=10.0,
        help="a loop is true within this many metres (default: %(default)s)",
    )
    return run_cli(p, _run, argv)


def _run(args: argparse.Namespace) -> None:
    summary = fleet_summary(args.fleet, args.radius)
    (args.fleet / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    for kind in ("inter_robot", "inter_session", "intra"):
        f = summary[kind]
        print(f"{kind}: {f['true']} true, {f['false']} false, precision {f['precision']}, "
              f"recall {f['recall']} of {f['possible']} possible")  # fmt: skip
    print(f"relocalisation: {summary['relocalisation']}")
    if summary["exchange"]:
        print(f"exchange: bytes per keyframe {summary['bytes_per_keyframe']}, per accepted "
              f"loop {summary['bytes_per_accepted_loop']}")  # fmt: skip
    for name, t in summary["trajectories"].items():
        print(f"{name}: {t}")
    print(f"targets: {summary['targets']}")
    for note in summary["notes"]:
        print(f"note: {note}")
    print(f"wrote {args.fleet / 'summary.json'}")


if __name__ == "__main__":
    sys.exit(main())
