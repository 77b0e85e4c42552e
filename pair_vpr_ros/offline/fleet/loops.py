"""`python -m pair_vpr_ros.offline.fleet.loops FLEET_DIR`: the fleet exchange's loops that no
replay found -> ``FLEET_DIR/exchange/added_loops.json`` (``pairvpr-posegraph --loops``).

``scripts/demo_fleet.sh`` finds loops between robots two ways, and the pose graph takes both:

* each drive's replay (``replay/<robot>_<session>/loops.json``) searches the earlier drives'
  saved maps (``--prior-map``): how a later session (robot a's day2) relocalises;
* the first sessions of the robots (one clock) run the fleet exchange together
  (``pairvpr-fleet-replay --out FLEET_DIR/exchange``): descriptors shared, candidates scored by
  their owner, ``inter_robot_loops.json``.

Both can accept the same keyframe pair, in either direction (b's replay matching a's keyframe,
or b's request scored by a, or a's request scored by b). The exchange's loops therefore **add to**
the replays' loops, each pair once: an accepted exchange loop joins only when no replay (and no
earlier exchange loop) accepted the same two keyframes, so the graph never gets one pair twice.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pair_vpr_ros.cli import run_cli
from pair_vpr_ros.errors import PoseGraphError
from pair_vpr_ros.offline.report.loop_io import json_records

EXCHANGE = "exchange"
LOOPS = "inter_robot_loops.json"
ADDED = "added_loops.json"

Pair = frozenset[tuple[str, str, float]]


def read_drives(fleet: Path) -> list[dict]:
    """``fleet.json``'s drives: robot, session, bag, in replay order."""
    return json.loads((fleet / "fleet.json").read_text())["drives"]


def replay_records(fleet: Path, drive: dict) -> list[dict]:
    """One drive's replay records (one per keyframe), in stamp order."""
    path = fleet / "replay" / f"{drive['robot']}_{drive['session']}" / "loops.json"
    if not path.is_file():
        raise PoseGraphError(f"no replay of {drive['robot']}/{drive['session']}: {path} missing")
    return sorted(json_records(path), key=lambda r: r["query_stamp"])


def pair_key(record: dict, robot: str = "", session: str = "") -> Pair:
    """The loop's two keyframes as (robot, session, stamp), unordered; empty ids are the
    replay's own (`robot`, `session`). Stamps rounded to the microsecond (both replays read
    the same bag stamps)."""
    ends = (
        (record.get("query_robot") or robot, record.get("query_session") or session,
         round(float(record["query_stamp"]), 6)),
        (record.get("match_robot") or robot, record.get("match_session") or session,
         round(float(record["match_stamp"]), 6)),
    )  # fmt: skip
    return frozenset(ends)


def exchange_loops(fleet: str | Path) -> tuple[list[dict], list[dict]] | None:
    """(every accepted exchange loop, those whose pair no replay nor earlier exchange loop
    accepted), or None when the fleet folder has no exchange run."""
    fleet = Path(fleet)
    path = fleet / EXCHANGE / LOOPS
    if not path.is_file():
        return None
    accepted = [r for r in json_records(path) if r.get("accepted")]
    seen: set[Pair] = set()
    for drive in read_drives(fleet):
        seen |= {pair_key(r, drive["robot"], drive["session"])
                 for r in replay_records(fleet, drive) if r.get("accepted")}  # fmt: skip
    added = []
    for record in accepted:
        key = pair_key(record)
        if key not in seen:
            seen.add(key)
            added.append(record)
    return accepted, added


def write_added_loops(fleet: str | Path) -> tuple[Path, int, int]:
    """Write ``exchange/added_loops.json``; (its path, loops added, accepted exchange loops)."""
    fleet = Path(fleet)
    found = exchange_loops(fleet)
    if found is None:
        raise PoseGraphError(
            f"no fleet exchange in {fleet}: {fleet / EXCHANGE / LOOPS} missing (run "
            f"pairvpr-fleet-replay --out {fleet / EXCHANGE} first)"
        )
    accepted, added = found
    path = fleet / EXCHANGE / ADDED
    path.write_text(json.dumps(added, indent=1) + "\n", encoding="utf-8")
    return path, len(added), len(accepted)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m pair_vpr_ros.offline.fleet.loops",
        description="the fleet exchange's accepted loops no replay found -> "
        "FLEET/exchange/added_loops.json (for pairvpr-posegraph --loops)",
    )
    p.add_argument("fleet", type=Path, help="folder scripts/demo_fleet.sh wrote (fleet.json)")
    return run_cli(p, _run, argv)


def _run(args: argparse.Namespace) -> None:
    path, added, accepted = write_added_loops(args.fleet)
    print(f"{added} of {accepted} accepted exchange loops added ({accepted - added} pairs "
          f"found by a replay already): {path}")  # fmt: skip


if __name__ == "__main__":
    sys.exit(main())
