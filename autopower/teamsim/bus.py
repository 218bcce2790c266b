"""A node's `Bus` on the simulated network: what Zenoh does for one process.

- ``publish`` puts a message to this process's own subscribers (as Zenoh does) and sends it over
  every session whose far end subscribes to a matching key.
- A liveliness token is seen by the processes this one has a session with; ``watch_liveliness``
  also reports the tokens already seen (Zenoh's history).
- A frozen process handles nothing: what arrives waits (its socket buffers) and is handled, in
  order, when it thaws. Every message and sight change is written to the trace when handled.
"""

from __future__ import annotations

import functools
import re
from typing import Callable

from autopower.protocol.keys import key_matches
from autopower.teamsim.network import SimNetwork
from autopower.teamsim.trace import Trace


@functools.lru_cache(maxsize=None)
def matcher(pattern: str) -> Callable[[str], bool]:
    """``key -> whether it matches pattern`` (`key_matches`), built once per pattern: no state per
    (pattern, key) pair, which a team of n robots has n^2 of (each robot's ``node/<r>/from/*``
    against every key the base station addresses)."""
    chunks = pattern.split("/")
    if "*" not in pattern:
        return pattern.__eq__
    if "**" not in chunks and all(c == "*" or "*" not in c for c in chunks):
        return re.compile("/".join("[^/]*" if c == "*" else re.escape(c) for c in chunks)).fullmatch
    return functools.partial(key_matches, pattern)


class _Handle:
    def __init__(self, close: Callable[[], None]):
        self._close = close

    def close(self) -> None:
        close, self._close = self._close, None
        if close is not None:
            close()


class SimBus:
    """One process's bus. ``after_event`` runs after each message or sight change it handled."""

    def __init__(self, node: str, network: SimNetwork, trace: Trace, after_event: Callable[[], None]):
        self.node = node
        self.network = network
        self.trace = trace
        self.after_event = after_event
        self.frozen = False
        self.closed = False
        self.subs: list[tuple[str, Callable[[str], object], Callable[[str, bytes], None]]] = []
        self._exact: dict[str, int] = {}  # the subscriptions' keys without wildcards (how many of each)
        self._wild: list[Callable[[str], object]] = []  # the others' matchers
        self.watchers: list[tuple[str, Callable[[str, bool], None]]] = []
        self.tokens: list[str] = []
        self.seen: dict[str, list[str]] = {}  # peer -> its tokens this process sees
        self.backlog: list[tuple] = []
        network.attach(node, self)

    # ---- the Bus protocol ------------------------------------------------------------------------
    zid = ""  # a simulated network: no Zenoh session, no kernel counting its links' bytes

    def links(self) -> dict[str, list[tuple[str, str]]]:
        return {}

    def publish(self, key: str, payload: bytes, *, reliable: bool = True) -> None:
        if self.closed:
            return
        payload = bytes(payload)
        if self.subscribes(key):
            self.network.scheduler.at(self.network.scheduler.now, self.arrive, self.node, key, payload)
        for peer in self.network.subscribers(self.node, key):
            self.network.transmit(self.node, peer, key, payload)

    def subscribe(self, key_expr: str, callback: Callable[[str, bytes], None]):
        entry = (key_expr, matcher(key_expr), callback)
        self.subs.append(entry)
        self._index()

        def unsubscribe() -> None:
            if entry in self.subs:
                self.subs.remove(entry)
                self._index()

        return _Handle(unsubscribe)

    def _index(self) -> None:
        self._exact, self._wild = {}, []
        for pattern, match, _ in self.subs:
            if "*" in pattern:
                self._wild.append(match)
            else:
                self._exact[pattern] = self._exact.get(pattern, 0) + 1
        self.network.subscriptions_changed()

    def declare_token(self, key: str):
        self.tokens.append(key)
        for peer in self.network.neighbours[self.node]:
            if self.network.connected(self.node, peer):
                self.network.endpoints[peer].token(self.node, key, True)

        def undeclare() -> None:
            if key in self.tokens:
                self.tokens.remove(key)
                for peer in self.network.neighbours[self.node]:
                    if self.network.connected(self.node, peer):
                        self.network.endpoints[peer].token(self.node, key, False)

        return _Handle(undeclare)

    def watch_liveliness(self, key_expr: str, callback: Callable[[str, bool], None]):
        match = matcher(key_expr)
        entry = (match, callback)
        self.watchers.append(entry)
        for peer, keys in self.seen.items():  # history: the tokens seen already
            for key in keys:
                if match(key):
                    self.network.scheduler.at(self.network.scheduler.now, self._sighted, peer, key, True)
        return _Handle(lambda: self.watchers.remove(entry) if entry in self.watchers else None)

    def serve(self, key: str, callback):
        return _Handle(lambda: None)

    def query(self, key: str, payload: bytes, timeout_s: float = 2.0) -> list[bytes]:
        return []

    def repeat_until_next(self, key: str, payload: bytes, after_s: float, every_s: float) -> None:
        """Nothing: a simulated loop is never late for its peers."""

    def flush_recording(self) -> None:
        """Nothing: the shells keep what a recording would (`Shell.commit_outputs`)."""

    repeated = 0

    def close(self) -> None:
        """The process ended: its sessions close, nothing more is handled."""
        if not self.closed:
            self.closed = True
            self.network.detach(self.node)

    # ---- from the network --------------------------------------------------------------------------
    def subscribes(self, key: str) -> bool:
        return key in self._exact or any(match(key) for match in self._wild)

    def arrive(self, sender: str, key: str, payload: bytes) -> None:
        if self.closed:
            return
        if self.frozen:
            self.backlog.append((self._handle, sender, key, payload))
        else:
            self._handle(sender, key, payload)

    def sight(self, peer: str, alive: bool) -> None:
        """A session to ``peer`` opened or closed: its tokens appear or vanish here."""
        if alive:
            for key in list(self.network.endpoints[peer].tokens):
                self.token(peer, key, True)
        else:
            for key in list(self.seen.get(peer, ())):
                self.token(peer, key, False)

    def token(self, peer: str, key: str, alive: bool) -> None:
        seen = self.seen.setdefault(peer, [])
        if alive == (key in seen):
            return
        if alive:
            seen.append(key)
        else:
            seen.remove(key)
        self._sighted(peer, key, alive)

    def _sighted(self, peer: str, key: str, alive: bool) -> None:
        if self.closed:
            return
        if self.frozen:
            self.backlog.append((self._handle_sight, peer, key, alive))
        else:
            self._handle_sight(peer, key, alive)

    # ---- handling -------------------------------------------------------------------------------------
    def _handle(self, sender: str, key: str, payload: bytes) -> None:
        self.trace.message(self.network.scheduler.now, sender, self.node, key, payload)
        for _, match, callback in list(self.subs):
            if match(key):
                callback(key, payload)
        self.after_event()

    def _handle_sight(self, peer: str, key: str, alive: bool) -> None:
        self.trace.liveliness(self.network.scheduler.now, self.node, peer, alive)
        for match, callback in list(self.watchers):
            if match(key):
                callback(key, alive)
        self.after_event()

    def thaw(self) -> None:
        """Handle, in order, what arrived while frozen."""
        self.frozen = False
        backlog, self.backlog = self.backlog, []
        for handle, *args in backlog:
            if self.closed:
                return
            handle(*args)
        self.network.frozen_changed(self.node)

    def freeze(self) -> None:
        self.frozen = True
        self.network.frozen_changed(self.node)
