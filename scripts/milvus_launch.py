"""Start PyPI milvus==2.3.5's `milvus-server` on exactly the ports asked for (run by
scripts/milvus_server.sh with the server venv's python; docs/milvus.md).

`milvus-server` probes each port by binding it without SO_REUSEADDR and silently takes the
next free one when that fails. Right after a `kill -9` the old server's ports still hold
TIME_WAIT connections for ~60 s, so a restart moved its health port from 9091 to 9092 (and
could move the client port off 19530): every client and health check then waited in vain (the
"restart not healthy within 3-7 min" of issue 35). Here every port is bound with SO_REUSEADDR
(as the Go server itself does), exactly, and a port that a live process holds stops the start
with a clear message instead of moving.

    python milvus_launch.py HEALTH_PORT milvus-server-arguments...
"""

from __future__ import annotations

import socket
import sys

import milvus


def bind_exactly(self, port: int):
    """MilvusServerConfig.resolve_port, without moving: -> (port, a socket holding it)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(("127.0.0.1", int(port)))
        sock.listen()
    except OSError as err:
        sock.close()
        sys.exit(
            f"milvus: port {port} is in use ({err}): another Milvus server (or program) runs "
            "on it; stop it, or give this one other ports (MILVUS_PORT_SHIFT)"
        )
    return int(port), sock


def main() -> None:
    milvus.MilvusServerConfig.resolve_port = bind_exactly
    milvus.default_server.webservice_port = int(sys.argv[1])  # the health check's port
    sys.argv = ["milvus-server", *sys.argv[2:]]
    milvus.main()


if __name__ == "__main__":
    main()
