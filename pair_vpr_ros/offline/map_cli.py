"""`pairvpr-map`: look into saved place maps and merge them (the library: `place_map.info`,
`place_map.merge`). Exit codes: `pair_vpr_ros.cli`.

    pairvpr-map info maps/site                 # keyframes per robot/session, model, index, sizes
    pairvpr-map info maps/site --json
    pairvpr-map merge maps/r1 maps/r2 --out maps/site
"""

from __future__ import annotations

import argparse
import json
import sys

from pair_vpr_ros.cli import run_cli
from pair_vpr_ros.place_map.index import INDEX_KINDS
from pair_vpr_ros.place_map.info import map_info
from pair_vpr_ros.place_map.merge import merge_maps


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pairvpr-map",
        description="Inspect and merge saved Pair-VPR place maps (never changes an input map).",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    info = sub.add_parser(
        "info", help="what a saved map holds: keyframes per robot and session, model, index, "
        "sizes on disk",
    )  # fmt: skip
    info.add_argument("map", metavar="DIR", help="folder of a saved place map")
    info.add_argument("--json", action="store_true", help="print one JSON object instead")
    merge = sub.add_parser(
        "merge", help="merge maps of one model into a new map (keyframe ids renumbered: the "
        "first map's first); crash-safe, inputs untouched",
    )  # fmt: skip
    merge.add_argument("maps", metavar="DIR", nargs="+", help="folders of saved place maps")
    merge.add_argument("--out", metavar="DIR", required=True, help="new folder (must not exist)")
    merge.add_argument(
        "--index", choices=INDEX_KINDS,
        help="index of the merged map (default: the first map's settings)",
    )  # fmt: skip
    merge.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> int | None:
    if args.command == "info":
        info = map_info(args.map)
        print(json.dumps(info.to_dict(), indent=1) if args.json else "\n".join(info.lines()))
        return None
    result = merge_maps(args.maps, args.out, index=args.index, progress=not args.quiet)
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    print(result.line())
    return None


if __name__ == "__main__":
    sys.exit(main())
