"""`pairvpr-fleet-replay`: several robots' bags replayed together with the fleet exchange
(``offline.fleet_replay.run_fleet``). Exit codes: ``pair_vpr_ros.cli``.

    pairvpr-fleet-replay --robot a 20261125T090000Z a.mcap --robot b 20261125T090500Z b.mcap \\
        --weights model.pth --params-file config/demo.yaml --out fleet_out
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pair_vpr_ros.cli import run_cli
from pair_vpr_ros.errors import ConfigError, UsageError
from pair_vpr_ros.identity import name_problem
from pair_vpr_ros.offline.fleet.replay import (
    FleetRobot,
    check_fleet_out,
    robot_fleet,
    run_fleet,
    write_fleet_run,
)
from pair_vpr_ros.params.configs import defaults, detector_config, geometry_config
from pair_vpr_ros.params.file import read_params_file
from pair_vpr_ros.params.fleet import fleet_config
from pair_vpr_ros.weights import load_model


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pairvpr-fleet-replay",
        description="Replay several robots' recordings in one process, each through its own "
        "loop-closure pipeline, with the fleet exchange between them (descriptors shared, "
        "candidates scored by their owner); writes inter-robot loops and bytes sent.",
    )
    p.add_argument(
        "--robot", nargs=3, action="append", metavar=("ROBOT", "SESSION", "SOURCE"),
        required=True, help="one robot: its id, its session id and its bag or image folder "
        "(repeat for each robot; ids must differ)",
    )  # fmt: skip
    p.add_argument("--weights", metavar="PATH", required=True, help="Pair-VPR checkpoint (.pth)")
    p.add_argument(
        "--params-file", metavar="YAML", help="vpr_node parameter file: detector, geometry and "
        "fleet_* settings (default: the node's defaults)",
    )  # fmt: skip
    p.add_argument("--topic", help="image topic of bags with several")
    p.add_argument(
        "--pose-topic", help="pose topic attached to keyframes (default: a bag's only one)"
    )
    p.add_argument("--device", default="cpu", help="torch device (default: %(default)s)")
    p.add_argument("--out", metavar="DIR", default="fleet_out", help="output folder")
    p.add_argument("--overwrite", action="store_true", help="replace a fleet run in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), _run, argv)


def check_robots(robots: list[FleetRobot]) -> None:
    """Every --robot checked before the work: ids by the identity rule, a source that exists."""
    for r in robots:
        flag = f"--robot {r.robot} {r.session} {r.source}"
        for what, value in (("robot id", r.robot), ("session id", r.session)):
            problem = name_problem(what, value)
            if problem:
                raise UsageError(f"{flag}: {problem}")
        if not Path(r.source).exists():
            raise UsageError(f"{flag}: no bag or image folder at {r.source}")


def fleet_peers(text: str, robots: list[FleetRobot]) -> tuple[str, ...]:
    """fleet_peers of a fleet run: ConfigError for a name that is no --robot of the run."""
    peers = tuple(p.strip() for p in text.split(",") if p.strip())
    names = [r.robot for r in robots]
    for peer in peers:
        problem = name_problem("fleet_peers robot", peer)
        if problem:
            raise ConfigError(problem)
        if peer not in names:
            raise ConfigError(
                f"fleet_peers names robot {peer!r}, which is no --robot of this run ({names}): "
                "list robots of the run, or '' for every robot"
            )
    for r in robots:  # one listed robot alone would listen to no robot: refused now
        robot_fleet({"peers": peers}, r.robot)
    return peers


def _run(args: argparse.Namespace) -> int:
    values = read_params_file(args.params_file) if args.params_file else defaults()
    robots = [FleetRobot(r, s, src, args.topic, args.pose_topic) for r, s, src in args.robot]
    if len(robots) < 2:
        raise UsageError("--robot: give at least two robots (the exchange is between robots)")
    check_robots(robots)
    # the fleet options of the parameter file, checked once with the first robot's identity;
    # fleet_peers: each robot listens to those of them other than itself (run_fleet)
    options = fleet_config({**values, "fleet_peers": ""}, robots[0].robot, robots[0].session)
    fleet = dict(budget=options.budget, period_s=options.period_s, top_k=options.top_k,
                 timeout_s=options.timeout_s, send_features=options.send_features,
                 select=options.select, peer_search=options.peer_search,
                 peers=fleet_peers(values["fleet_peers"], robots))  # fmt: skip
    out = check_fleet_out(args.out, args.overwrite)
    model = load_model(args.weights, device=args.device)
    run = run_fleet(robots, model, detector_config(values), fleet, geometry_config(values),
                    progress=not args.quiet)  # fmt: skip
    write_fleet_run(run, out)
    t = run.totals()
    print(
        f"{t['keyframes']} keyframes, {t['inter_robot_loops']} inter-robot loops "
        f"({t['inter_robot_rejected']} rejected); {t['descriptor_bytes_per_keyframe']:.0f} B "
        f"descriptor and {t['bytes_per_keyframe']:.0f} B in all per keyframe; outputs in {out}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
