"""Console entry points of the nodes, kept light: a stop signal while the heavy modules (rclpy,
torch) still import ends the process quietly, as one after start-up does.

Before this, Ctrl-C in the first second or two of `ros2 run pair_vpr_ros vpr_node` (imports)
printed a KeyboardInterrupt traceback and exited with -2.

In a venv set up with the pip ROS wheels, the C libraries (rclpy's and the typed messages',
`<venv>/lib`) are found through LD_LIBRARY_PATH, which the wheels' start-up hook sets once per
process tree and then marks done. A node started by another environment's `ros2 launch` or
`ros2 run` inherits that environment's path and the mark, so this venv's lib/ is missing and the
typed messages cannot load. Before anything imports rclpy, the entry adds this venv's library
folders and starts itself again, once; should that fail, the node still runs with its typed
topic off (one warning, `ros.outputs`).
"""

from __future__ import annotations

import glob
import os
import signal
import sys
import sysconfig

EXIT_OK = 0  # = cli.EXIT_OK; not imported: this module must import nothing heavy
REEXEC_MARK = "PAIRVPR_LIBRARY_PATH_SET"  # set in the started-again process: never twice


def library_dirs() -> list[str]:
    """This venv's folders of ROS C libraries: <venv>/lib and site-packages/ros_*.libs
    (none outside a venv: an apt or colcon install sets its paths by `source setup.bash`)."""
    if sys.prefix == sys.base_prefix:
        return []
    site = sysconfig.get_paths()["purelib"]
    dirs = [os.path.join(sys.prefix, "lib"), *sorted(glob.glob(os.path.join(site, "ros_*.libs")))]
    return [d for d in dirs if os.path.isdir(d)]


def find_own_libraries(environ: dict[str, str] | None = None) -> dict[str, str] | None:
    """The environment to start again with when a library folder of this venv is missing from
    LD_LIBRARY_PATH (they go first), else None."""
    environ = os.environ if environ is None else environ
    if environ.get(REEXEC_MARK) or not sys.platform.startswith("linux"):
        return None
    have = [p for p in environ.get("LD_LIBRARY_PATH", "").split(os.pathsep) if p]
    missing = [d for d in library_dirs() if d not in have]
    if not missing:
        return None
    return {**environ, "LD_LIBRARY_PATH": os.pathsep.join(missing + have), REEXEC_MARK: "1"}


def _start_again_if_needed() -> None:
    environ = find_own_libraries()
    if environ is not None:
        try:
            os.execve(sys.executable, sys.orig_argv, environ)
        except OSError as err:  # go on: the typed topic is then off, with one warning
            sys.stderr.write(f"pair_vpr_ros: cannot restart with this venv's libraries: {err}\n")


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _run(module: str, argv: list[str] | None) -> int:
    """Import `module` and run its `main(argv)`; a stop signal before main takes over the
    signals (during the imports) is a clean stop."""
    _start_again_if_needed()  # before rclpy loads: LD_LIBRARY_PATH is read at process start
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
