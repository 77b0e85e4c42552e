"""pairvpr-bag-play: play a rosbag2 into the ROS graph in (scaled) real time, for the pip set-up
that has no `ros2 bag` (rclpy + rosbags).

    pairvpr-bag-play demo_out/demo_world.mcap --rate 1.0 --clock --wait 30

Every message goes out as it is stored (CDR bytes turned into the rclpy type, no conversion),
on its own topic, at `stamp offset / rate` after the first one (a player that falls behind
sends at once and says so at the end). `--clock` also publishes rosgraph_msgs/Clock on /clock
at each message's bag time (for nodes run with use_sim_time). `--wait S` first waits up to S s
until every subscriber the graph shows on the played topics is connected, so the first frames
are not lost to discovery. Publishers are reliable, keep-last 100.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import ReaderError

from pair_vpr_ros.cli import nonnegative_float, positive_float, run_cli
from pair_vpr_ros.errors import BagError, UsageError

DEPTH = 100


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pairvpr-bag-play",
        description="Play a rosbag2 (.mcap / .db3 file or bag folder) into the ROS graph.",
    )
    p.add_argument("bag", type=Path, help="rosbag2 folder, .mcap or .db3 file")
    p.add_argument("--rate", type=positive_float, default=1.0, help="speed factor (1: real time)")
    p.add_argument("--clock", action="store_true", help="also publish /clock (bag time)")
    p.add_argument("--topics", nargs="+", default=None, help="play only these (default: all)")
    p.add_argument(
        "--wait", type=nonnegative_float, default=0.0,
        help="wait up to this many seconds for the graph's subscribers to connect first",
    )  # fmt: skip
    p.add_argument(
        "--wait-for", nargs="+", default=[], metavar="TOPIC",
        help="with --wait: these topics must have a connected subscriber before playing",
    )  # fmt: skip
    return p


def open_bag(path: Path) -> AnyReader:
    """An open reader of `path`; BagError says what is wrong with it."""
    if not path.exists():
        raise BagError(f"bag {path} does not exist: give a rosbag2 folder, .mcap or .db3 file")
    reader = AnyReader([path])
    try:
        reader.open()
    except (ReaderError, AnyReaderError) as err:
        raise BagError(f"bag {path} cannot be read ({err}): is it a rosbag2 bag?") from err
    return reader


def message_class(msgtype: str) -> type:
    """`sensor_msgs/msg/Image` -> the rclpy class (BagError where it is not installed)."""
    package, kind, name = msgtype.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except (ImportError, AttributeError) as err:
        raise BagError(f"message type {msgtype} is not installed here ({err})") from err


def chosen_connections(reader: AnyReader, topics: list[str] | None, path: Path) -> list:
    have = sorted({c.topic for c in reader.connections})
    missing = sorted(set(topics or []) - set(have))
    if missing:
        raise UsageError(f"--topics {' '.join(missing)}: not in bag {path} (its topics: "
                         f"{', '.join(have)})")  # fmt: skip
    return [c for c in reader.connections if topics is None or c.topic in topics]


def wait_for_subscribers(node, publishers: dict, seconds: float, needed: list[str]) -> bool:
    """Wait until each publisher is connected to every subscriber the graph shows on its
    topic, one topic has any, and each topic in `needed` has one -> True; False after
    `seconds`."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        counts = {t: (p.get_subscription_count(), node.count_subscribers(t))
                  for t, p in publishers.items()}  # fmt: skip
        ready = all(counts[t][0] >= 1 for t in needed)
        if (
            ready
            and any(s for _, s in counts.values())
            and all(m >= s for m, s in counts.values())
        ):
            return True
        time.sleep(0.1)
    return False


def play(args: argparse.Namespace) -> int:
    import rclpy
    from rclpy.serialization import deserialize_message
    from rosgraph_msgs.msg import Clock

    reader = open_bag(args.bag)
    try:
        connections = chosen_connections(reader, args.topics, args.bag)
        chosen_connections(reader, args.wait_for or None, args.bag)  # each one in the bag
        classes = {c.msgtype: message_class(c.msgtype) for c in connections}
        rclpy.init()
        node = rclpy.create_node("pairvpr_bag_play")
        publishers = {c.topic: node.create_publisher(classes[c.msgtype], c.topic, DEPTH)
                      for c in connections}  # fmt: skip
        clock = node.create_publisher(Clock, "/clock", DEPTH) if args.clock else None
        if args.wait and not wait_for_subscribers(node, publishers, args.wait, args.wait_for):
            print(f"pairvpr-bag-play: no subscriber connected within {args.wait:g} s; playing",
                  file=sys.stderr)  # fmt: skip
        sent, late, start, first = 0, 0, time.monotonic(), None
        for connection, stamp, raw in reader.messages(connections=connections):
            first = stamp if first is None else first
            due = start + (stamp - first) / 1e9 / args.rate
            ahead = due - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)
            elif ahead < -0.1:
                late += 1
            if clock is not None:
                tick = Clock()
                tick.clock.sec, tick.clock.nanosec = divmod(stamp, 1_000_000_000)
                clock.publish(tick)
            publishers[connection.topic].publish(
                deserialize_message(bytes(raw), classes[connection.msgtype])
            )
            sent += 1
        time.sleep(0.5)  # reliable delivery of the last messages before the publishers go
        took = time.monotonic() - start
        print(f"pairvpr-bag-play: {sent} messages on {len(publishers)} topics in {took:.1f} s "
              f"(rate {args.rate:g}; {late} sent more than 0.1 s late)")  # fmt: skip
        node.destroy_node()
        rclpy.try_shutdown()
    finally:
        reader.close()
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), play, argv)


if __name__ == "__main__":
    sys.exit(main())
