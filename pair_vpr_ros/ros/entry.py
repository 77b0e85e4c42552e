"""Console entry points of the nodes, kept light: a stop signal while the heavy modules (rclpy,
torch) still import ends the process quietly, as one after start-up does.

Before this, Ctrl-C in the first second or two of `ros2 run pair_vpr_ros vpr_node` (imports)
printed a KeyboardInterrupt traceback and exited with -2.
"""

from __future__ import annotations

import signal
import sys

EXIT_OK = 0  # = cli.EXIT_OK; not imported: this module must import nothing heavy


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _run(module: str, argv: list[str] | None) -> int:
    """Import `module` and run its `main(argv)`; a stop signal before main takes over the
    signals (during the imports) is a clean stop."""
    signal.signal(signal.SIGTERM, _interrupt)  # SIGINT raises KeyboardInterrupt already
    try:
        main = __import__(module, fromlist=["main"]).main
        return main(argv)
    except KeyboardInterrupt:
        return EXIT_OK


def vpr_node(argv: list[str] | None = None) -> int:
    return _run("pair_vpr_ros.ros.node", argv)


def posegraph_node(argv: list[str] | None = None) -> int:
    return _run("pair_vpr_ros.ros.posegraph_node", argv)


if __name__ == "__main__":
    sys.exit(vpr_node())
