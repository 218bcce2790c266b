"""Cheap deterministic stand-ins for a chain's source and components (the simulator's default).

A source's frame carries its robot and seq. A stage's output is a pure function of its input
(`transform`), so what a sink must receive for each seq can be computed without running the team
(`expected_output`). A stage's state is the next seq it expects: an input that skips or repeats
one raises, and the node stops the stage (`StageFailed`); state that migrates keeps the check.
"""

from __future__ import annotations

import zlib

import msgpack

from autopower.chains.teammap import decode_join
from autopower.model.scenario import Chain


def transform(component_type: str, data: bytes) -> bytes:
    """A stand-in stage's output for ``data``: the frame's robot and seq, and a checksum of both."""
    robot, seq, *_ = msgpack.unpackb(data)
    return msgpack.packb([robot, seq, zlib.crc32(data + component_type.encode())])


def source_frame(robot: str, seq: int) -> bytes:
    return msgpack.packb([robot, seq])


def expected_output(chain: Chain, seq: int) -> bytes:
    """What the sink of ``chain`` must receive for ``seq`` (stand-ins, a chain without fan-in)."""
    data = source_frame(chain.source, seq)
    for stage in chain.stages:
        data = transform(stage.component, data)
    return data


class StandInSource:
    def __init__(self, component_type: str, robot: str, seed: int, parameters: dict | None = None):
        self.component_type, self.robot = component_type, robot

    def produce(self, seq: int) -> bytes:
        return source_frame(self.robot, seq)

    def ground_truth(self, seq: int) -> dict:
        return {}


class StandInComponent:
    def __init__(self, component_type: str, robot: str, seed: int, parameters: dict | None = None):
        self.component_type, self.robot = component_type, robot
        self.next_seq: int | None = None

    def run(self, payload: bytes) -> bytes:
        data = msgpack.unpackb(payload)
        if isinstance(data, dict):  # a fan-in stage's input: one join step (`chains.teammap.encode_join`)
            return self._run_join(payload)
        robot, seq, *_ = data
        if robot != self.robot:
            raise ValueError(f"an input of {robot} given to {self.robot}'s {self.component_type}")
        if self.next_seq is not None and seq != self.next_seq:
            raise ValueError(f"expected seq {self.next_seq}, got {seq}: an input was lost, repeated or reordered")
        self.next_seq = seq + 1
        return transform(self.component_type, payload)

    def _run_join(self, payload: bytes) -> bytes:
        """A join's output: this node's name, the step, a checksum of the step's inputs. Its state
        is the next step it may run: steps only go forward (empty ones are skipped), never twice."""
        step = decode_join(payload)["step"]
        if self.next_seq is not None and step < self.next_seq:
            raise ValueError(f"join step {step} after step {self.next_seq - 1}: a step ran twice or out of order")
        self.next_seq = step + 1
        return msgpack.packb([self.robot, step, zlib.crc32(payload + self.component_type.encode())])

    def export_state(self) -> bytes:
        return msgpack.packb(self.next_seq)

    def import_state(self, state: bytes) -> None:
        self.next_seq = msgpack.unpackb(state)
