"""Every message AutoPower processes exchange, one frozen dataclass each, grouped by direction.

Data plane (``node/<n>/data``, CongestionControl.BLOCK): `Packet`, carrying an encoded
`ChainFrame` or `StateTransfer` hop by hop along a source route.
Coordinator -> node (``node/<n>/control``, BLOCK): `Assign`, `Prepare`, `MigrateOut`, `Release`, or a
`Batch` of them;
and a robot's plans: `PlanUpdate`, or a new plan as its `PlanChange` from the one that robot holds
(`autopower.basestation.delivery`).
Node -> coordinator (``base/inbox``, BLOCK): `Prepared`, `StageReady`, `StageFailed`, or a `Batch` of them.
Coordinator -> base stations and recorders (``base/plan``, BLOCK): `PlanUpdate`, or a new plan as
its `PlanChange` from the one before (`autopower.protocol.plans`).
Telemetry (``status/<n>``, DROP): `NodeStatus`, whole or as its `StatusDelta` from the last whole
one, for base stations (and each process's recording).
Between robots (``peer/<n>``, DROP): `PeerStatus`, the part of a status the robots use.
Addressed in the sender's name (``node/<to>/from/<n>``, DROP): `Ack`, what n consumed of the
chains ``to`` sent it; from the base station, its `PeerStatus` as robot ``to`` acts on it.
Operator -> coordinator (query on ``base/operator``): `ChainCommand`, `MigrateCommand`,
`AutoCommand`, `LinkCommand`, `SnapshotRequest`; reply `OperatorReply`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from autopower.protocol.codec import message, struct

# ---------------------------------------------------------------------------------------------
# shared value types
# ---------------------------------------------------------------------------------------------


@struct
@dataclass(frozen=True, kw_only=True)
class LinkInfo:
    a: str
    b: str
    medium: str


@struct
@dataclass(frozen=True, kw_only=True)
class OperatorSettings:
    """What the operator decided, carried in every plan and echoed in every robot's status, so
    that a base station taking over the team keeps it (pins, disabled chains, links declared down,
    radio changes): it lives with the team, not in the process that heard the command."""

    pins: dict[str, str] = field(default_factory=dict)  # stage -> node (`migrate`)
    disabled: tuple[str, ...] = ()  # chains stopped by the operator or by a failed component
    cuts: tuple[tuple[str, str], ...] = ()  # links the operator declared down
    radios: dict[str, tuple[str | None, str | None]] = field(default_factory=dict)  # node -> (laptop-robot, robot-robot) medium


@struct
@dataclass(frozen=True, kw_only=True)
class MissionInfo:
    """What every node must agree on to meter the same mission."""

    scenario: str  # the scenario's name (every node loads the same file)
    accounting: str  # "paper" | "physical"
    epoch_unix: float  # wall time (time.time()) of virtual t = 0
    speed: float  # virtual seconds per wall second
    energies_j: dict[str, float]  # starting battery per robot


@struct
@dataclass(frozen=True, kw_only=True)
class SourceStats:
    run: int  # activation number of the chain (a disable/enable starts a new run)
    produced: int  # frames produced in this run (the next seq)
    missed: int  # periods skipped because the agent was late, over every run (like produced_total)
    produced_total: int
    # of missed: those the agent found when it came back after being stopped for a second or more
    # (SIGSTOP, a suspended host), which no speed-up is to blame for (`agent.stages.STOPPED_AFTER_S`)
    missed_stopped: int = 0


@struct
@dataclass(frozen=True, kw_only=True)
class SinkStats:
    run: int
    received: int  # distinct outputs of this run
    duplicates: int  # outputs seen twice (must stay 0)
    contiguous: int  # every seq below this has arrived
    max_seq: int  # highest seq seen, -1 for none
    stale: int  # outputs of an older run that arrived late
    latency_ms_p50: float
    latency_ms_max: float
    received_total: int
    duplicates_total: int
    digest: int  # sequencing.fold_digest over the outputs of seqs < contiguous
    redundant_total: int = 0  # copies of a retransmitted output that arrived twice (expected, dropped)
    given_up_total: int = 0  # seqs the sink stopped waiting for (sequencing.SINK_MAX_AHEAD): lost unless late


MAX_MISSING_RANGES = 256  # missing ranges in one `Consumed` (the lowest ones)


@struct
@dataclass(frozen=True, kw_only=True)
class Consumed:
    """What the consumer of one hop of a chain has taken in: a stage's input gate or a sink.

    Published with every status in an `Ack`, it acknowledges frames to whoever sent them (their
    custody buffers drop what was consumed and resend what a later report still lacks).
    """

    run: int
    generation: int  # of the stage instance (0 for a sink): the newest report wins
    next_seq: int  # every seq below has been consumed
    max_seq: int  # highest seq received so far, -1 for none
    # Seqs in [next_seq, max_seq] not received, as inclusive (first, last) ranges, sorted and
    # disjoint, the lowest MAX_MISSING_RANGES of them. Ranges, not seqs: a robot's full hold drops
    # hundreds of results in a row, which never come; as a list of seqs they would fill the report,
    # and the frames lost past them would never be named, so never resent.
    missing: tuple[tuple[int, int], ...]

    def __post_init__(self) -> None:
        if len(self.missing) > MAX_MISSING_RANGES:
            raise ValueError(f"{len(self.missing)} missing ranges; at most {MAX_MISSING_RANGES}")
        low = self.next_seq
        for first, last in self.missing:
            if not low <= first <= last <= self.max_seq:
                raise ValueError(f"missing range ({first}, {last}) is not sorted, disjoint and within "
                                 f"[{self.next_seq}, {self.max_seq}]")
            low = last + 2  # disjoint and not adjacent: adjacent ranges are one range


@message
@dataclass(frozen=True, kw_only=True)
class Ack:
    """What one node has consumed, for one of the nodes that sent it frames: their custody's acknowledgement.

    Sent with every status on `Keys.ack` (to, from), one per producer, with the hops of the chains
    that producer sends or holds (`NodeStatus.acks_wanted`): a robot hears the acknowledgements of
    the chains it feeds, not the whole team's.
    """

    KIND = "ack"
    node: str  # who consumed (the sender)
    t_unix: float
    consumed: dict[str, Consumed]  # "chain#target" -> what the node took in
    # wall seconds the oldest chain data waiting in the node's event queue had waited (see
    # `NodeStatus.queue_wait_s`): ``consumed`` speaks for frames sent before t_unix - queue_wait_s
    queue_wait_s: float = 0.0
    # a sink's hop -> what it got of the runs before its current one that it still remembers
    # (`SinkLedger.older`): an older run's results are not obsolete while the sink still takes them
    older: dict[str, tuple[Consumed, ...]] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# data plane
# ---------------------------------------------------------------------------------------------


@message
@dataclass(frozen=True, kw_only=True)
class Packet:
    """One routed hop. Forwarders only read the header: body stays encoded end to end."""

    KIND = "packet"
    path: tuple[str, ...]  # nodes from the sender to the destination (the model's shortest route)
    media: tuple[str, ...]  # medium of each hop, fixed by the first sender, len(path) - 1
    hop: int  # index in path of the node this copy is addressed to
    charge_bytes: int  # bytes the radios are charged for (the chain's declared message size)
    weight: float  # modelled messages this real message stands for (model.flow_weight)
    purpose: str  # "chain" | "migration" | "recovery" (a resent frame) | "backlog" (held back): which meter bucket pays
    chain: str
    body: bytes  # an encoded ChainFrame or StateTransfer

    def __post_init__(self) -> None:
        problem = Packet.problem(self.path, self.media, self.hop, self.charge_bytes, self.weight, self.purpose)
        if problem is not None:
            raise ValueError(problem)

    @staticmethod
    def problem(path, media, hop: int, charge_bytes: int, weight: float, purpose: str) -> str | None:
        """What is wrong with a packet header (None: nothing); also checked by `protocol.forwarding`."""
        if len(path) < 2 or len(media) != len(path) - 1:
            return f"path {path} needs >= 2 nodes and one medium per hop"
        if not 1 <= hop < len(path):
            return f"hop {hop} outside path of {len(path)} nodes"
        if charge_bytes < 0 or weight < 0:
            return "charge_bytes and weight must be >= 0"
        if purpose not in ("chain", "migration", "recovery", "backlog"):
            return f"purpose {purpose!r} is not chain, migration, recovery or backlog"
        return None


@message
@dataclass(frozen=True, kw_only=True)
class ChainFrame:
    """The input of stage ``target`` (``target == len(stages)``: the output for the sink)."""

    KIND = "frame"
    chain: str
    run: int
    seq: int
    target: int
    t_virtual: float  # when the source produced it
    t_unix: float  # wall time of production, for latency measurements
    payload_len: int  # real length; payload is zero-padded to the chain's declared size
    payload: bytes
    # 0: the first copy; > 0: a copy that may repeat an earlier one (its producer's n-th resend, or
    # a stage restarted without state recomputing inputs its lost predecessor may have run)
    attempt: int = 0
    # the lowest seq of this hop (chain, target, run) its producer still holds unacknowledged: all
    # below were consumed by some instance of the consumer, so a gate waiting for them can move on,
    # and a stage started without state starts here (the producer resends what it then lacks)
    floor: int | None = None

    def __post_init__(self) -> None:
        if self.seq < 0 or self.target < 0 or self.run < 0 or self.attempt < 0:
            raise ValueError("seq, target, run and attempt must be >= 0")
        if not 0 <= self.payload_len <= len(self.payload):
            raise ValueError(f"payload_len {self.payload_len} exceeds the {len(self.payload)} B payload")

    def data(self) -> bytes:
        return self.payload[: self.payload_len]


@message
@dataclass(frozen=True, kw_only=True)
class StateTransfer:
    """A migrating stage: its exported state, where its input sequence resumes, pending inputs."""

    KIND = "state"
    stage: str
    generation: int
    chain: str
    run: int
    state: bytes
    next_seq: int | None  # None: the old host never ran it (resume from the first input seen)
    pending: tuple[ChainFrame, ...]  # inputs that reached the old host but were not run
    t_export_unix: float  # when the old host stopped it (downtime measurement)
    from_node: str
    resent: tuple[int, ...] = ()  # recent seqs that first arrived as resends: their late originals are redundant
    # the stage's outputs the old host keeps in memory only, its consumer's acknowledgement not yet in:
    # the new host keeps them too (a crash of the old host would lose them, their inputs run)
    outputs: tuple[ChainFrame, ...] = ()


# ---------------------------------------------------------------------------------------------
# coordinator -> node
# ---------------------------------------------------------------------------------------------


@message
@dataclass(frozen=True, kw_only=True)
class Assign:
    """Host a new instance of a stage, with no state."""

    KIND = "assign"
    stage: str
    generation: int
    chain: str
    run: int
    resume_seq: int | None  # 0 for a new run; None after a failure (start at the first input seen)


@message
@dataclass(frozen=True, kw_only=True)
class Prepare:
    """A stage is about to move here: buffer its inputs, answer `Prepared`."""

    KIND = "prepare"
    stage: str
    generation: int
    from_node: str


@message
@dataclass(frozen=True, kw_only=True)
class MigrateOut:
    """Stop the stage after its current run, export its state, send it to ``to_node``."""

    KIND = "migrate-out"
    stage: str
    generation: int
    to_node: str


@message
@dataclass(frozen=True, kw_only=True)
class Release:
    """Stop hosting a stage and forget it (its chain was disabled or dropped)."""

    KIND = "release"
    stage: str
    generation: int


# ---------------------------------------------------------------------------------------------
# node -> coordinator
# ---------------------------------------------------------------------------------------------


@message
@dataclass(frozen=True, kw_only=True)
class Prepared:
    KIND = "prepared"
    stage: str
    generation: int
    node: str


@message
@dataclass(frozen=True, kw_only=True)
class StageReady:
    """A stage now runs here (after `Assign`, or after importing a `StateTransfer`)."""

    KIND = "stage-ready"
    stage: str
    generation: int
    node: str
    imported_state: bool
    resume_seq: int | None
    downtime_ms: float  # old host stopped it -> it runs here; 0 for a fresh assignment
    buffered: int  # inputs held during the move


@message
@dataclass(frozen=True, kw_only=True)
class StageFailed:
    """A stage's component failed here: it raised, returned something that is not bytes, wrote more
    than the chain declares, or hung (``what``); or its state would not import into a new instance
    (``what = "import-failed"``: the migration is refused and the stage keeps running here); or the
    source of the chain whose first stage is ``stage`` hung on ``node`` (``what = "source-hung"``,
    ``generation`` -1)."""

    KIND = "stage-failed"
    stage: str
    generation: int
    node: str
    what: str  # "raised" | "not-bytes" | "oversize" | "hung" | "export-failed" | "import-failed" | "source-hung"
    detail: str  # the exception text (one line, bounded)
    running: bool  # the stage still runs on `node` (a refused migration) or it has stopped


# ---------------------------------------------------------------------------------------------
# coordinator -> everyone
# ---------------------------------------------------------------------------------------------


@message
@dataclass(frozen=True, kw_only=True)
class PlanUpdate:
    KIND = "plan"
    epoch: int  # increases with every change (continued by a base station that takes over)
    mission: MissionInfo
    placement: dict[str, str]  # stage -> node where it runs now (confirmed)
    running: dict[str, int]  # chain -> run number, for chains whose sources should produce
    links: tuple[LinkInfo, ...]  # the network the data follows (routing and radio media)
    predicted_w: dict[str, float]  # the model's power per robot for this placement
    predicted_lifetime_s: float | None
    plan_t_virtual: float  # when this placement's prediction starts
    policy: str = ""  # what decided it (autopower.policies's name)
    reasons: tuple[str, ...] = ()  # why, in the policy's words (for the operator and the recording)
    levels: dict[str, str] = field(default_factory=dict)  # robot -> DVFS frequency level (model.dvfs)
    variants: dict[str, str] = field(default_factory=dict)  # chain -> quality variant (model.variants)
    # which start of a base station made it: plans are ordered by (incarnation, epoch), so a base
    # station that takes over a running team (incarnation + 1) is followed whatever its epoch
    incarnation: int = 0
    leader: str = ""  # that base station's instance id: two base stations at once tell each other apart
    operator: OperatorSettings = field(default_factory=OperatorSettings)  # kept by a base station that takes over


@message
@dataclass(frozen=True, kw_only=True)
class PlanChange:
    """A plan as its change from the plan before it (`autopower.protocol.plans`).

    A new plan moves a few stages; the whole one grows with the team (14.5 kB at 100 robots, most
    of it links that did not change). A node that holds the plan this one follows (same leader
    and incarnation, ``base_epoch``, and the same bytes: ``base_digest``) applies it and checks
    the result against ``digest``; any other node ignores it and is sent the whole plan
    (`Coordinator.resend_plan`), as one that missed a plan always was.
    """

    KIND = "plan-change"
    epoch: int
    incarnation: int
    leader: str
    base_epoch: int
    base_digest: bytes  # `plan_digest` of the plan it follows
    digest: bytes  # `plan_digest` of the plan it makes
    placement: dict[str, str]  # entries new or changed
    unplaced: tuple[str, ...]  # stages the plan no longer places
    running: dict[str, int]
    not_running: tuple[str, ...]
    links: tuple[LinkInfo, ...]  # links new or with another medium (plans list their links sorted)
    links_gone: tuple[LinkInfo, ...]
    predicted_w: dict[str, float]
    not_predicted: tuple[str, ...]
    levels: dict[str, str]
    not_levelled: tuple[str, ...]
    variants: dict[str, str]
    not_varied: tuple[str, ...]
    predicted_lifetime_s: float | None
    plan_t_virtual: float
    # None: as in the plan before (a plan made when a stage lands keeps its decision's reasons)
    policy: str | None
    reasons: tuple[str, ...] | None
    operator: OperatorSettings | None


# ---------------------------------------------------------------------------------------------
# telemetry
# ---------------------------------------------------------------------------------------------


@message
@dataclass(frozen=True, kw_only=True)
class NodeStatus:
    KIND = "status"
    node: str
    t_virtual: float
    t_unix: float
    plan_epoch: int
    initial_j: float | None  # None for mains power
    battery_j: float | None
    energy_j: dict[str, float]  # consumed so far, by part ("cpu_idle", "cpu_busy", "802.11a:send", ...)
    power_w: dict[str, float]  # by part, averaged over the last status window
    cpu_utilisation: float  # modelled (component latencies on this platform), last window
    hosted: dict[str, str]  # stage -> lifecycle state
    sources: dict[str, SourceStats]
    sinks: dict[str, SinkStats]
    links: dict[str, bool]  # neighbour -> its liveliness token is visible from here
    runs: dict[str, int]  # stage -> runs executed here
    compute_ms: dict[str, float]  # stage -> real mean run time on this machine
    queue_depth: int
    errors: dict[str, int]  # dropped garbled messages, unroutable frames, ...
    counters: dict[str, int]  # normal events: forwarded packets, missed periods, ...
    depleted: bool
    # the chains whose acknowledgements this node needs (it sends their frames or holds some in
    # custody): a consumer sends its `Ack` to these nodes as well as to the producers its plan names
    acks_wanted: tuple[str, ...] = ()
    failed: dict[str, str] = field(default_factory=dict)  # stage -> why its component was stopped here
    # what a base station taking over a running team learns from it (see basestation/takeover.py)
    plan_incarnation: int = 0  # with plan_epoch: the plan this node runs
    plan_leader: str = ""  # the base station that made it (`PlanUpdate.leader`)
    mission: MissionInfo | None = None  # the mission clock and starting energies it meters (None: not started)
    generations: dict[str, int] = field(default_factory=dict)  # stage -> generation of the instance hosted here
    plan_operator: OperatorSettings | None = None  # the operator's settings in the plan it runs
    # wall seconds until this node's next status at the latest: its status period, or a longer one at
    # rest (nothing new to say; `runtime.cadence`); 0: not said (the receiver's own period applies)
    next_status_s: float = 0.0
    # the model's power for what this node runs (its plan's prediction for it; after a subgroup
    # commit, the subgroup's): what the recording checks the meter against. None: no prediction
    model_w: float | None = None
    # a restarted process: (virtual time its predecessor's metering stops, watts the meter charges
    # for the time the robot was without it: idle CPU, radios asleep), so the model follows it too
    down: tuple[float, float] | None = None
    # wall seconds the oldest chain data waiting in this node's event queue had waited when the status
    # was made: whatever reached it longer ago than that has been taken in, so `consumed` speaks for the
    # frames sent before (t_unix - queue_wait_s) only (its producers' custody waits that much longer)
    queue_wait_s: float = 0.0
    # this node's Zenoh session id: its peers attribute the bytes of their links to it by it
    # (`node.control_meter`); "" where there is no Zenoh session (a simulation)
    zid: str = ""
    # (sent, received) bytes on every link since the mission started, as the kernel counted them, and
    # of these the control plane's (everything but the chain packets): `runtime.link_traffic`
    link_bytes: tuple[int, int] = (0, 0)
    control_bytes: tuple[int, int] = (0, 0)
    # (sent, received) TCP segments on those links: the packets its radios carry, whatever their size
    link_packets: tuple[int, int] = (0, 0)
    # CPU seconds on the computer running the node since the mission started in this process: the
    # runtime's own (all but component code; charged as `cpu_runtime` through its platform's
    # slowdown, `Metering.charge_runtime`) and its component code's
    runtime_cpu_s: float = 0.0
    component_cpu_s: float = 0.0
    # which process of the node this is: a number drawn when it starts (`NodeRuntime.process`). A base
    # station that lost a chain's source robot tells by it that the robot came back as the process it
    # lost (cut off, frozen) and still holds the chain's position (`basestation.runs`); 0: not said
    process: int = 0
    # chain -> the run whose source position this process took from its crashed predecessor's saved
    # state (`Resuming.resume`): its seqs in that run go on after the predecessor's. A restarted
    # process that names a chain's run here does not source that run's seqs again from 0
    resumed: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 0 <= self.process < 2**63:
            raise ValueError(f"process {self.process} is outside [0, 2**63)")
        for chain, run in self.resumed.items():
            if run < 0 or chain not in self.sources:  # a source taken up is one the process reports
                raise ValueError(f"resumed {chain!r} run {run}: not a run of a source this status reports")


@message
@dataclass(frozen=True, kw_only=True)
class StatusDelta:
    """A `NodeStatus` as its change from the last whole one its sender sent (the keyframe,
    `autopower.protocol.statuses`): most of a status (stages, links, sinks' runs, counters, the
    energy parts' names) repeats from one status to the next; its clock and meters do not.

    ``changes`` maps a `NodeStatus` field's position to its new value as the wire carries it
    (`codec.wire_fields`); a map field's value is ``[entries new or changed, keys gone]``, a key
    the keyframe has given by its position in the keyframe's map, a new one by its name. Fields
    absent are as in the keyframe. A receiver that holds the keyframe (its ``t_unix`` is
    ``key_t``) builds the whole status and decodes it as strictly as one sent whole; one that
    does not waits for the next keyframe (the delta still says the sender is there).
    """

    KIND = "status-delta"
    node: str
    t_unix: float
    key_t: float  # `NodeStatus.t_unix` of the keyframe this is the change from
    changes: dict[int, Any]


@message
@dataclass(frozen=True, kw_only=True)
class PeerStatus:
    """What a robot needs of every other node, with each status: that it is there (the heartbeat its
    silence detector listens to), what it sees (relaying), what it runs and its battery (subgroup
    rounds, a newer instance of a stage) and which acknowledgements it wants. The rest of a
    `NodeStatus` (sink ledgers, meters, counters, errors) goes to base stations only: the robots
    read none of it, and the base station's ledgers grew with the team (5.7 kB of its 13.9 kB
    status at 30 robots, sent to every robot each status period).
    """

    KIND = "peer-status"
    node: str
    t_unix: float
    plan_epoch: int
    battery_j: float | None
    hosted: dict[str, str]  # stage -> lifecycle state
    generations: dict[str, int]  # stage -> generation of the instance hosted here
    links: dict[str, bool]  # the nodes whose liveliness token is visible from here (True only)
    acks_wanted: tuple[str, ...] = ()  # see `NodeStatus.acks_wanted`
    down: tuple[float, float] | None = None  # see `NodeStatus.down`
    next_status_s: float = 0.0  # see `NodeStatus.next_status_s`
    zid: str = ""  # see `NodeStatus.zid`
    # None: ``links`` lists the nodes in sight. A tuple: the sender sees every member of the team but
    # itself and these, and ``links`` is empty (a base station sees most of its team: its view to a
    # robot names the few out of sight, not the whole team, `basestation.peer_view`). `sees` reads both.
    unseen: tuple[str, ...] | None = None
    # The sender could not apply the receiver's last status change (it missed the whole status the
    # change was from): the receiver sends its next status whole (`protocol.statuses`).
    send_whole: bool = False

    def sees(self, team: Iterable[str]) -> set[str]:
        """The nodes the sender has in sight; ``team``: every member's name (the ``unseen`` form)."""
        if self.unseen is None:
            return {n for n, up in self.links.items() if up}
        return set(team) - set(self.unseen) - {self.node}

    @classmethod
    def of(cls, status: NodeStatus) -> "PeerStatus":
        return cls(node=status.node, t_unix=status.t_unix, plan_epoch=status.plan_epoch,
                   battery_j=status.battery_j, hosted=status.hosted, generations=status.generations,
                   links={n: True for n, up in status.links.items() if up}, acks_wanted=status.acks_wanted,
                   down=status.down, next_status_s=status.next_status_s, zid=status.zid)


# ---------------------------------------------------------------------------------------------
# operator
# ---------------------------------------------------------------------------------------------


@message
@dataclass(frozen=True, kw_only=True)
class ChainCommand:
    KIND = "op-chain"
    chain: str
    enabled: bool


@message
@dataclass(frozen=True, kw_only=True)
class MigrateCommand:
    """Pin a stage to a node (forces a migration; overrides the planner until `AutoCommand`)."""

    KIND = "op-migrate"
    stage: str
    to_node: str


@message
@dataclass(frozen=True, kw_only=True)
class AutoCommand:
    """Drop every pin: placement follows the planner again."""

    KIND = "op-auto"


@message
@dataclass(frozen=True, kw_only=True)
class LinkCommand:
    """A node's radio changes (the paper's V.C fault), or a link goes down (medium None, down)."""

    KIND = "op-link"
    node: str
    laptop_robot: str | None = None
    robot_robot: str | None = None
    down_peer: str | None = None


@message
@dataclass(frozen=True, kw_only=True)
class SnapshotRequest:
    """The team's snapshot. ``until_ready_s`` > 0: answered once the team is ready (every stage where
    the plan wants it) or when that many seconds have passed, whichever comes first: one query
    waits for the team instead of a snapshot built, sent and decoded every few tens of ms."""

    KIND = "op-snapshot"
    until_ready_s: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.until_ready_s <= MAX_UNTIL_READY_S:
            raise ValueError(f"until_ready_s {self.until_ready_s} is outside [0, {MAX_UNTIL_READY_S:g}] s")


MAX_UNTIL_READY_S = 30.0  # a base station holds an operator's query no longer than this


@message
@dataclass(frozen=True, kw_only=True)
class OperatorReply:
    KIND = "op-reply"
    ok: bool
    message: str
    snapshot: dict[str, Any] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# application-level relay (zenoh peers do not relay for each other)
# ---------------------------------------------------------------------------------------------


@message
@dataclass(frozen=True, kw_only=True)
class Relayed:
    """A control-plane message carried hop by hop through agents to a node with no direct link.

    ``key`` and ``payload`` are what the origin would have published had the link been up; the
    destination handles them exactly as if they had arrived on ``key``.
    """

    KIND = "relayed"
    path: tuple[str, ...]  # origin ... destination
    hop: int  # index in path of the node this copy is addressed to
    key: str
    payload: bytes
    # the author's certificate and signature (`runtime.signatures`); empty in an --insecure team
    signer_cert: bytes = b""
    signature: bytes = b""

    def __post_init__(self) -> None:
        if len(self.path) < 2 or not 1 <= self.hop < len(self.path):
            raise ValueError(f"relay path {self.path} with hop {self.hop} is not valid")


# ---------------------------------------------------------------------------------------------
# subgroup agreement among robots (no base station): propose -> accept -> commit
# ---------------------------------------------------------------------------------------------


@struct
@dataclass(frozen=True, kw_only=True)
class SubgroupMove:
    stage: str
    from_node: str | None  # None: started fresh here (its host is out of reach)
    to_node: str


@message
@dataclass(frozen=True, kw_only=True)
class SubgroupPropose:
    KIND = "sg-propose"
    round_id: str
    leader: str
    members: tuple[str, ...]
    placement: dict[str, str]  # stage -> node after the commit (the subgroup's stages)
    moves: tuple[SubgroupMove, ...]
    generation: int  # generation of every move of this round
    reason: str
    # the author's certificate and signature (`runtime.signatures`); empty in an --insecure team
    signer_cert: bytes = b""
    signature: bytes = b""


@message
@dataclass(frozen=True, kw_only=True)
class SubgroupVote:
    KIND = "sg-vote"
    round_id: str
    node: str
    accept: bool
    reason: str
    # the author's certificate and signature (`runtime.signatures`); empty in an --insecure team
    signer_cert: bytes = b""
    signature: bytes = b""


@message
@dataclass(frozen=True, kw_only=True)
class SubgroupDecision:
    KIND = "sg-decision"
    round_id: str
    commit: bool
    reason: str
    # the author's certificate and signature (`runtime.signatures`); empty in an --insecure team
    signer_cert: bytes = b""
    signature: bytes = b""


@message
@dataclass(frozen=True, kw_only=True)
class Batch:
    """Several messages for one key in one put, each encoded on its own: the coordinator's orders
    to one node in one reconcile (`CONTROL_MESSAGES`), and that node's answers to them
    (`INBOX_MESSAGES`). A plan that places 150 stages on 30 robots is 30 puts and 30 answers, not
    150 of each. Its receiver checks every item before it acts on any (`autopower.protocol.batch`)."""

    KIND = "batch"
    items: tuple[bytes, ...]


OPERATOR_COMMANDS = (ChainCommand, MigrateCommand, AutoCommand, LinkCommand, SnapshotRequest)
CONTROL_MESSAGES = (Assign, Prepare, MigrateOut, Release)
INBOX_MESSAGES = (Prepared, StageReady, StageFailed)
