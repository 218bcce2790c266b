"""Wire protocol: messages, the strict msgpack codec, and the key expressions.

May import: `autopower.errors` only: every process and the recorder decode the same bytes.
"""

from autopower.protocol.batch import MAX_BATCH_ITEMS, batched, unbatch
from autopower.protocol.codec import PROTOCOL_VERSION, decode, encode, message_kinds
from autopower.protocol.keys import Keys, check_name
from autopower.protocol.messages import (
    CONTROL_MESSAGES,
    INBOX_MESSAGES,
    OPERATOR_COMMANDS,
    Ack,
    Assign,
    AutoCommand,
    Batch,
    ChainCommand,
    ChainFrame,
    Consumed,
    LinkCommand,
    LinkInfo,
    MigrateCommand,
    MigrateOut,
    MissionInfo,
    NodeStatus,
    OperatorReply,
    OperatorSettings,
    Packet,
    PeerStatus,
    PlanChange,
    PlanUpdate,
    Prepare,
    Prepared,
    Relayed,
    Release,
    SinkStats,
    SnapshotRequest,
    SourceStats,
    StageFailed,
    StageReady,
    StateTransfer,
    StatusDelta,
    SubgroupDecision,
    SubgroupMove,
    SubgroupPropose,
    SubgroupVote,
)

__all__ = [
    "CONTROL_MESSAGES", "INBOX_MESSAGES", "MAX_BATCH_ITEMS", "batched", "unbatch", "OPERATOR_COMMANDS", "PROTOCOL_VERSION",
    "Ack", "Assign", "AutoCommand", "Batch", "ChainCommand", "ChainFrame", "Keys", "LinkCommand", "LinkInfo", "OperatorSettings",
    "MigrateCommand", "MigrateOut", "MissionInfo", "NodeStatus", "OperatorReply", "Packet", "PeerStatus",
    "PlanChange", "PlanUpdate", "Prepare", "Prepared", "Relayed", "Release", "SinkStats", "Consumed", "SnapshotRequest", "SourceStats",
    "StageFailed", "StageReady", "StateTransfer", "StatusDelta", "SubgroupDecision", "SubgroupMove", "SubgroupPropose", "SubgroupVote", "check_name", "decode", "encode", "message_kinds",
]
