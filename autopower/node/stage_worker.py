"""The child side of stage worker processes (`autopower.node.workers`): a zygote and its workers.

``python -c "from autopower.node.stage_worker import main; main()" FD`` is the *zygote*: started once per node with an
explicit environment, it imports the built-in components (numpy, the blob finder, the localiser)
and then waits on its end of a socketpair (fd ``FD``). For each ``fork`` request it forks a
*worker* (a single-threaded process forks safely) and hands the node the worker's end of a new
socketpair (SCM_RIGHTS) with its pid. A worker builds one stage's component and serves
``run`` / ``export`` / ``import`` one at a time, in order, until its socket closes.

Every message is a msgpack array behind an 8-byte header; its last element, when it is bytes,
travels raw after it (`send`). What a worker returns is data
(bytes, a type name, an exception's text), never a pickled object: the node treats it as it
treats what a component returns in-process, checked before use. Both processes die with their
parent (PR_SET_PDEATHSIG), so a node killed with SIGKILL leaves no workers behind.
"""

from __future__ import annotations

import ctypes
import importlib
import os
import signal
import socket
import struct
import sys
import time

import msgpack

MAX_MESSAGE = 256 * 2**20  # bytes: a frame or a state larger than this is refused (bounded memory)
_HEADER = struct.Struct(">II")  # the msgpack part's length, the raw part's (NO_RAW: none)
NO_RAW = 0xFFFFFFFF
SOCKET_BUFFER = 2 << 20  # bytes: a window of camera frames (the kernel caps it at net.core.wmem_max)


def send(sock: socket.socket, msg: list) -> None:
    """A message; a bytes last element (a camera frame, an output, a state) travels raw after the
    msgpack part, never copied into it (230 KB frames at several hundred a second)."""
    raw = msg[-1] if msg and isinstance(msg[-1], (bytes, bytearray, memoryview)) else None
    body = msgpack.packb(msg if raw is None else msg[:-1], use_bin_type=True)
    parts = [_HEADER.pack(len(body), NO_RAW if raw is None else len(raw)), body]
    if raw is not None:
        parts.append(raw)
    sent = sock.sendmsg(parts)
    for part in parts:  # a full socket buffer took part of it: the rest in order, without copying
        if sent >= len(part):
            sent -= len(part)
            continue
        sock.sendall(memoryview(part)[sent:])
        sent = 0


def receive(sock: socket.socket) -> list | None:
    """The next message (its raw part as its last element); None at end of stream."""
    head = _read_exactly(sock, _HEADER.size)
    if head is None:
        return None
    size, raw_size = _HEADER.unpack(head)
    if size > MAX_MESSAGE or (raw_size != NO_RAW and raw_size > MAX_MESSAGE):
        raise ValueError(f"a stage worker message of {max(size, raw_size)} B exceeds {MAX_MESSAGE} B")
    body = _read_exactly(sock, size)
    if body is None:
        return None
    msg = msgpack.unpackb(body, raw=False, strict_map_key=False)
    if not isinstance(msg, list):
        raise ValueError("a stage worker message is not a list")
    if raw_size != NO_RAW:
        raw = _read_exactly(sock, raw_size)
        if raw is None:
            return None
        msg.append(raw)
    return msg


def _read_exactly(sock: socket.socket, n: int) -> bytes | None:
    if n == 0:
        return b""
    first = sock.recv(n, socket.MSG_WAITALL)  # one copy: the kernel's buffer into a bytes object
    if len(first) == n or not first:
        return first or None
    buf = bytearray(first)
    while len(buf) < n:  # interrupted: the rest piece by piece
        more = sock.recv(n - len(buf))
        if not more:
            return None
        buf += more
    return bytes(buf)


def _die_with_parent() -> None:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux: the socket's end of stream still ends a worker
        pass


def _resolve(path: str):
    module, _, attr = path.partition(":")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def build(recipe: list):
    """The component a recipe names (`workers.recipe_for` writes them)."""
    how = recipe[0]
    if how == "registry":  # a built-in component type
        from autopower.chains import make_component

        _, kind, robot, seed, parameters = recipe
        return make_component(kind, robot, seed, parameters) if parameters else make_component(kind, robot, seed)
    if how == "class":  # a plug-in: Cls(robot, seed)
        _, path, robot, seed = recipe
        return _resolve(path)(robot, seed)
    if how == "call":  # the node's own factory (an importable function or class)
        _, path, kind, robot, seed, parameters = recipe
        factory = _resolve(path)
        return factory(kind, robot, seed, parameters) if parameters else factory(kind, robot, seed)
    raise ValueError(f"unknown recipe {how!r}")


def _error(exc: BaseException) -> list:
    return ["err", type(exc).__name__, str(exc)[:2000]]


def serve(sock: socket.socket) -> None:
    """A worker: one component, one call at a time, until the node closes the socket."""
    component = None
    while True:
        msg = receive(sock)
        if msg is None:
            return
        op = msg[0]
        try:
            if op == "build":
                component = build(msg[1])
                reply = ["ok", {"export": callable(getattr(component, "export_state", None)),
                                "import": callable(getattr(component, "import_state", None))}]
            elif op == "run":
                started = time.perf_counter()
                out = component.run(msg[1])
                spent = time.perf_counter() - started
                reply = ["ok", spent, out] if isinstance(out, bytes) else ["bad", type(out).__name__]
            elif op == "export":
                out = component.export_state()
                reply = ["ok", out] if isinstance(out, bytes) else ["bad", type(out).__name__]
            elif op == "import":
                component.import_state(msg[1])
                reply = ["ok", None]
            else:
                reply = ["err", "ValueError", f"unknown operation {op!r}"]
        except Exception as exc:  # the component's: handed to the node, which decides
            reply = _error(exc)
        send(sock, reply)


def zygote(sock: socket.socket) -> None:
    """Fork a worker per request; reap them automatically (SIGCHLD ignored)."""
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the node decides
    import autopower.chains  # noqa: F401  (what every worker needs, imported once, before forking)

    send(sock, ["ready", os.getpid()])
    while True:
        msg = receive(sock)
        if msg is None or msg[0] != "fork":
            return
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        for end in (mine, theirs):  # room for a whole camera frame: one send, one receive
            end.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER)
            end.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER)
        pid = os.fork()
        if pid == 0:  # the worker
            try:
                sock.close()
                theirs.close()
                _die_with_parent()
                signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                serve(mine)
            finally:
                os._exit(0)
        mine.close()
        socket.send_fds(sock, [msgpack.packb(["forked", pid])], [theirs.fileno()])
        theirs.close()


def main() -> None:
    _die_with_parent()
    sock = socket.socket(fileno=int(sys.argv[1]))
    try:
        zygote(sock)
    except (BrokenPipeError, ConnectionResetError, KeyboardInterrupt):
        pass


if __name__ == "__main__":
    main()
