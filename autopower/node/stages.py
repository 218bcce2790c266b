"""What a node hosts: stage instances, source runners, their lifecycle, and frame padding."""

from __future__ import annotations

import enum
import zlib
from dataclasses import dataclass, field
from typing import Any

from autopower.errors import ProtocolError
from autopower.model.scenario import Chain, Scenario, Stage
from autopower.node.sequencing import SequenceGate
from autopower.protocol import (
    ChainFrame,
)

MAX_FORWARDS = 16  # a frame bounced more often than this between pointers is parked instead
ORPHAN_LIMIT = 256  # frames held for a stage this node is about to host (a transient window)
# A sensor keeps capturing while the node is busy: its driver queues this many captures (as a V4L2
# camera's buffer ring does), which the node takes late, each with its own capture time. Only a
# capture older than that is lost: a missed period. Without it a node with two sources on one loop
# missed a camera period whenever a laser scan took longer than one camera period to produce
# (every scan at x100, where the camera's period is 2.5 ms of wall time).
SENSOR_QUEUE = 8
# A node whose loop comes back this long (wall seconds) after its last turn was stopped, not slow:
# SIGSTOP (`autopower fault freeze`), a suspended host, a debugger. The periods it then finds
# missed are counted apart (`missed_stopped`), so that `up` does not blame the speed-up for them.
# A loop starved by an overloaded machine turns many times a second and misses periods on most
# of its turns; it is never away for a whole second at once without missing periods before too.
STOPPED_AFTER_S = 1.0


class Lifecycle(enum.Enum):
    STARTING = "starting"
    RUNNING = "running"
    DRAINING = "draining"
    MIGRATED = "migrated"
    FAILED = "failed"  # its component raised, returned garbage or hung: stopped here, inputs dropped


def chain_seed(scenario: Scenario, chain: Chain) -> int:
    """The same seed on every node, so a source and its component agree on the world."""
    return zlib.crc32(f"{scenario.name}/{chain.name}".encode())


def pad(payload: bytes, size: int, what: str) -> bytes:
    """Zero-pad a real payload to the chain's declared message size.

    The radios are charged for the declared sizes (the model's), so the bytes on the wire are
    made exactly that long too; a payload longer than declared is a scenario error.
    """
    if len(payload) > size:
        raise ProtocolError(f"{what}: a real payload of {len(payload)} B exceeds the chain's declared "
                            f"message_bytes {size}; raise message_bytes in the scenario")
    return payload + bytes(size - len(payload))


@dataclass
class HostedStage:
    stage: Stage
    chain: Chain
    index: int
    generation: int
    lifecycle: Lifecycle
    run: int = 0
    component: Any = None
    gate: SequenceGate = field(default_factory=SequenceGate)
    buffer: list[ChainFrame] = field(default_factory=list)  # inputs held while STARTING
    forward_to: str | None = None  # MIGRATED: where late inputs go
    runs: int = 0
    compute_s: float = 0.0
    failure: str | None = None  # FAILED: why
    # The answer sent to the order that made this instance (Prepared, then StageReady), and for
    # a MIGRATED one the state it shipped (the migration's generation, its new host, the encoded
    # StateTransfer; the body dropped, b"", once the plan shows the stage landed): sent again as
    # they were if the base station repeats the order, which it does when the order or its answer
    # was lost (`basestation.placing.Placement.resend_orders`).
    answer: bytes = b""
    shipped: tuple[int, str, bytes] | None = None
    imported: bool = False  # its component imported a migrated state (`Hosting.on_state`)
    # Mission time this host was named for the stage (its first order here): the model prices the
    # stage here from then on, and inputs captured before it where the stage was then
    # (`Frames.ran` meters their runs here as a backlog). An instance that replaces one still
    # here (prepared, running, draining) keeps its time.
    placed_t: float = 0.0

    def carries_state(self) -> bool:
        """Whether its component may hold state from earlier inputs: it ran one here, or it imported
        the state of an instance that did. A fresh component has seen nothing: it may start anywhere."""
        return self.imported or self.gate.released > 0


def placed_since(current: HostedStage | None, now: float) -> float:
    """`HostedStage.placed_t` of a new instance that replaces ``current`` on this host: its time
    while it is still here (prepared, running, draining), else ``now``."""
    here = current is not None and current.lifecycle in (Lifecycle.STARTING, Lifecycle.RUNNING, Lifecycle.DRAINING)
    return current.placed_t if here else now


@dataclass
class SourceRunner:
    chain: Chain
    source: Any
    run: int
    next_t: float
    seq: int = 0
    missed: int = 0
    produced_total: int = 0
    missed_stopped: int = 0  # of missed: found after the node was stopped (`STOPPED_AFTER_S`)
