"""A flap's phases follow the times its fault record gives, however long a switch takes."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

from autopower.launch.faults import FaultController

SLOW_SWITCH_S = 0.3  # two tc calls on a loaded machine


class _SlowLink:
    """A testbed link (it has `drop`) whose every switch takes SLOW_SWITCH_S; it notes when each took effect."""

    def __init__(self):
        self.is_cut, self.drops, self.rate = False, {}, None
        self.switched: list[tuple[str, float]] = []
        self.lock = threading.Lock()

    def drop(self, *args):  # pragma: no cover - only its presence matters (a testbed link)
        raise AssertionError

    def _switch(self, to: str) -> None:
        time.sleep(SLOW_SWITCH_S)
        with self.lock:
            self.is_cut = to == "down"
            self.switched.append((to, time.monotonic()))

    def cut(self) -> None:
        self._switch("down")

    def uncut(self) -> None:
        self._switch("up")

    def heal(self) -> None:
        self.is_cut = False


def test_a_flaps_switches_start_on_the_faults_own_clock_not_after_its_first_slow_cut():
    link = _SlowLink()
    team = SimpleNamespace(proxy=lambda a, b: link, proxies={frozenset(("a", "b")): link},
                           spec=SimpleNamespace(record_dir=None))
    controller = FaultController(team)
    t0 = time.monotonic()  # the fault's t_unix is taken within microseconds of this
    controller.apply({"op": "flap", "a": "a", "b": "b", "up_s": 0.5, "down_s": 0.5})
    time.sleep(1.0 + 2 * SLOW_SWITCH_S)
    controller.apply({"op": "heal", "a": "a", "b": "b"})
    controller.close()
    ups = [t for to, t in link.switched if to == "up"]
    downs = [t for to, t in link.switched if to == "down"]
    # due at t0 + 0.5 (up) and t0 + 1.0 (down); each takes SLOW_SWITCH_S to take effect. Timed from
    # the end of the first cut, they came SLOW_SWITCH_S later still.
    assert ups and ups[0] - t0 < 0.5 + SLOW_SWITCH_S + 0.1, [(to, round(t - t0, 3)) for to, t in link.switched]
    assert len(downs) >= 2 and downs[1] - t0 < 1.0 + SLOW_SWITCH_S + 0.1, \
        [(to, round(t - t0, 3)) for to, t in link.switched]
