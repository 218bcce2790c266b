"""Carry the operator's connections from the host's loopback into the base station's namespace.

The testbed's base station lives in a network namespace of its own, which the host cannot reach
(nothing is added to the host's network). `up`-style supervision and `autopower status` still
need it: the supervisor binds a listening socket on the host's 127.0.0.1 and hands it to this
process, started inside the base station's namespace (``ip netns exec``), which forwards each
connection to the base station's listener there. Raw bytes: the mutual TLS session is end to
end between the operator and the base station, and the base station's access control applies.

``python -m autopower.launch.nsbridge FD PORT``
"""

from __future__ import annotations

import signal
import socket
import sys
import threading

from autopower.launch.linkproxy import LinkProxy


def main() -> None:
    fd, port = int(sys.argv[1]), int(sys.argv[2])
    server = socket.socket(fileno=fd)
    server.settimeout(0.2)
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    with LinkProxy("operator", port, server=server):
        done.wait()


if __name__ == "__main__":
    main()
