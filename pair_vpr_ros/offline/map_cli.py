"""`pairvpr-map`: look into saved place maps, merge or compact them, prune a Milvus collection
(the library: `place_map.info`, `place_map.merge`, `place_map.growth.compact`,
`place_map.milvus.prune`). Exit codes: `pair_vpr_ros.cli`.

    pairvpr-map info maps/site                 # keyframes per robot/session, model, index, sizes
    pairvpr-map info maps/site --json
    pairvpr-map merge maps/r1 maps/r2 --out maps/site
    pairvpr-map compact maps/site --out maps/site-compact   # growth policy + dense codec p4
    pairvpr-map prune-milvus maps/site.db --maps maps       # lists stale rows; --yes removes
"""

from __future__ import annotations

import argparse
import json
import sys

from pair_vpr_ros.cli import finite_float, run_cli
from pair_vpr_ros.place_map.dense_codec import CODECS, DEFAULT_CODEC
from pair_vpr_ros.place_map.growth.compact import compact_map
from pair_vpr_ros.place_map.growth.policy import GrowthConfig
from pair_vpr_ros.place_map.index import INDEX_KINDS
from pair_vpr_ros.place_map.info import map_info
from pair_vpr_ros.place_map.merge import merge_maps
from pair_vpr_ros.place_map.milvus.prune import prune_milvus


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pairvpr-map",
        description="Inspect and merge saved Pair-VPR place maps (never changes an input map); "
        "remove Milvus rows no saved map refers to.",
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
    merge.add_argument(
        "--milvus-uri", metavar="URI", help="index milvus: a milvus-lite file (.db) or "
        "http(s)://host:port (default: the first map's; needed when it is not a milvus map)",
    )  # fmt: skip
    merge.add_argument(
        "--milvus-collection", metavar="NAME",
        help="index milvus: the collection (default: the first map's)",
    )  # fmt: skip
    merge.add_argument("--quiet", action="store_true", help="no progress bar")
    _compact_parser(sub)
    _prune_parser(sub)
    return p


def _compact_parser(sub) -> None:
    compact = sub.add_parser(
        "compact", help="rewrite a map into a new folder without the keyframes its stored "
        "appearance signatures and links say are represented by another (map_growth places), "
        "dense tokens in --codec; crash-safe, the input untouched",
    )  # fmt: skip
    compact.add_argument("map", metavar="IN", help="folder of a saved place map (format 3)")
    compact.add_argument("--out", metavar="OUT", required=True, help="new folder (must not exist)")
    compact.add_argument(
        "--codec", choices=CODECS, default=DEFAULT_CODEC,
        help="how OUT stores dense tokens (default %(default)s: 4 bits a value on a basis)",
    )  # fmt: skip
    compact.add_argument(
        "--no-policy", action="store_true",
        help="keep every keyframe: only re-encode the dense tokens",
    )  # fmt: skip
    compact.add_argument(
        "--exclude-recent-s", type=float, default=30.0, metavar="S",
        help="a keyframe never represents one of its own robot-session this close in time "
        "(the node's exclude_recent_s; default %(default)s)",
    )  # fmt: skip
    compact.add_argument(
        "--score-threshold", type=finite_float, default=0.0, metavar="S",
        help="the detector's score_threshold: a keyframe is represented only by one its own "
        "re-ranking scored at least this (the re-rank score its link keeps; default "
        "%(default)s, the node's default)",
    )  # fmt: skip
    compact.add_argument(
        "--fingerprint", metavar="FP",
        help="refuse a map of another model (the fingerprint `pairvpr-map info` prints)",
    )  # fmt: skip


def _prune_parser(sub) -> None:
    prune = sub.add_parser(
        "prune-milvus", help="list the rows of a Milvus keyframe collection that no saved map "
        "refers to (runs never saved, keyframes past a map's last save); --yes removes them",
    )  # fmt: skip
    prune.add_argument(
        "uri", metavar="URI",
        help="the maps' milvus_uri: a milvus-lite file (.db) or http(s)://host:port",
    )  # fmt: skip
    prune.add_argument(
        "--maps", metavar="DIR", nargs="+", required=True,
        help="folders holding every saved map of the collection (searched recursively): rows "
        "of maps not found there count as stale (such a map gets them back on its next load)",
    )  # fmt: skip
    prune.add_argument(
        "--collection", default="pairvpr_keyframes", metavar="NAME",
        help="the collection (milvus_collection; default %(default)s)",
    )  # fmt: skip
    prune.add_argument(
        "--token-env", default="PAIRVPR_MILVUS_TOKEN", metavar="NAME",
        help="environment variable holding the server token (default %(default)s)",
    )  # fmt: skip
    prune.add_argument(
        "--yes", action="store_true",
        help="remove the stale rows (default: a dry run that only lists them); on a server, "
        "stop the robots writing the collection first: a live map's unsaved rows are stale",
    )  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), _run, argv)


def _run(args: argparse.Namespace) -> int | None:
    if args.command == "info":
        info = map_info(args.map)
        print(json.dumps(info.to_dict(), indent=1) if args.json else "\n".join(info.lines()))
        return None
    if args.command == "compact":
        growth = GrowthConfig(exclude_recent_s=args.exclude_recent_s)
        compacted = compact_map(args.map, args.out, codec=args.codec, policy=not args.no_policy,
                                growth=growth, fingerprint=args.fingerprint,
                                score_threshold=args.score_threshold)  # fmt: skip
        for warning in compacted.warnings:
            print(f"warning: {warning}", file=sys.stderr)
        for note in compacted.notes:
            print(f"note: {note}", file=sys.stderr)
        print(compacted.line())
        return None
    if args.command == "prune-milvus":
        pruned = prune_milvus(args.uri, args.maps, args.collection, args.yes, args.token_env)
        print("\n".join(pruned.lines()))
        return None
    result = merge_maps(
        args.maps, args.out, index=args.index, progress=not args.quiet,
        milvus_uri=args.milvus_uri, milvus_collection=args.milvus_collection,
    )  # fmt: skip
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    print(result.line())
    return None


if __name__ == "__main__":
    sys.exit(main())
