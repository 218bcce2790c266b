"""What the oracle checks a "died with the crashed process" label against: where a chain's frames
were at the moment a process was killed.

A restarted node names the outputs of its chains that may have died with its crashed process
(`Resuming._died_with_process`, `_died_in_hand`). The label moves an output out of "lost", so
it needs evidence: at some kill, the killed process had the frame in hand (custody, a hold, a
stage's gate, start-up buffer or worker, an orphan, a migration's state with its pending inputs,
unread messages, an output its sink had not committed) or on the wire, and no other process had
it or was about to. The simulator sees all of that at the instant of each kill (`World.crash`);
an output labelled died that no kill took is a violation (it was lost elsewhere, not in a crash).
The process is not checked: a frame one process's restart names may have gone to another that
was killed with it in hand (a result its stage's host held for a sink that had crashed).

A kill also takes the inputs a stage's gate elsewhere holds behind one it took (`stranded`): a stage
runs its inputs in order, each once, so an input it waits for that died leaves those behind it
runnable only past a gap, which a stand-in stage refuses as a skipped input (`teamsim.components`).
A chain whose source robot is killed runs again when the robot is back (in its run if the restarted
process took its position up from its saved state, else in the next: `basestation.runs`): its stage's
host released the instance that waited behind the gap (the chain stopped), so those inputs are never run.
"""

from __future__ import annotations

from collections.abc import Iterable

from autopower.errors import ProtocolError
from autopower.protocol import ChainFrame, Packet, Relayed, StateTransfer, decode

Key = tuple[str, int, int]  # (chain, run, seq)


def frames_of(payload: bytes) -> set[Key]:
    """The chain frames a message carries: a packet's frame, a migration's pending inputs, what a
    relayed message carries (none for anything else, or a garbled one)."""
    return _keys(_frames(payload))


def _frames(payload: bytes) -> tuple[ChainFrame, ...]:
    try:
        msg = decode(payload, (Packet, Relayed, StateTransfer, ChainFrame))
    except ProtocolError:
        return ()
    if isinstance(msg, Packet):
        return _frames(msg.body)
    if isinstance(msg, Relayed):
        return _frames(msg.payload)
    if isinstance(msg, StateTransfer):
        return tuple(msg.pending)
    return (msg,)


def only_in(world, node: str) -> set[Key]:
    """The chain frames that die if ``node``'s process is killed now: those it has in hand (or sent
    and still on the wire) that no other process has in hand or on its way. ``world``: the run's
    `teamsim.team.World` (its shells and network)."""
    mine = in_hands(world, node)
    for payload in world.network.in_transit(sender=node):
        mine |= frames_of(payload)
    if not mine:
        return mine
    others: set[Key] = set()
    for other, shell in world.shells.items():
        if other != node and shell.up and shell.rt is not None:
            others |= in_hands(world, other)
    for payload in world.network.in_transit(but=node):
        others |= frames_of(payload)
    taken = mine - others
    return taken | stranded(world, node, taken)


def stranded(world, node: str, taken: set[Key]) -> set[Key]:
    """The inputs stranded behind one the kill of ``node`` takes (``taken``): for each stage's gate on
    another live process, the first seq it waits for (from ``next_seq``) that the kill took, if any,
    and the inputs of its hop above that seq waiting in the gate or on their way (from any sender but
    ``node``). The gate runs its inputs in order: those can be run only past a gap (the module's rules)."""
    gates: list[tuple[str, int, int, int]] = []  # (chain, run, target, the first seq taken it waits for)
    out: set[Key] = set()
    for other, shell in world.shells.items():
        if other == node or not shell.up or shell.rt is None:
            continue
        for hosted in shell.rt.hosted.values():
            gate = hosted.gate
            if gate.next_seq is None:
                continue
            chain, run = hosted.chain.name, hosted.run
            dead = next((seq for seq in range(gate.next_seq, gate.next_seq + gate.max_pending + 1)
                         if seq not in gate.pending and (chain, run, seq) in taken), None)
            if dead is None:
                continue
            gates.append((chain, run, hosted.index, dead))
            out.update((f.chain, f.run, f.seq) for f in gate.pending.values() if f.seq > dead)
    if gates:
        for payload in world.network.in_transit(but=node):
            for f in _frames(payload):
                if any((f.chain, f.run, f.target) == g[:3] and f.seq > g[3] for g in gates):
                    out.add((f.chain, f.run, f.seq))
    return out


def in_hands(world, node: str) -> set[Key]:
    """Every chain frame ``node``'s process has in hand: in custody, a hold, a stage's gate, start-up
    buffer or worker, an orphan, a migration's state, its unread messages (frozen), or an output its
    sink delivered and has not committed yet."""
    shell = world.shells[node]
    rt = shell.rt
    # custody, hold, gates, buffers, workers, orphans: what the node names in flight at a clean stop
    out = {(chain, run, seq) for (chain, run), seqs in rt.in_flight_at_stop().items() for seq in seqs}
    for _, body, _ in rt.hosting.parked_transfers:
        out |= frames_of(body)
    for hosted in rt.hosted.values():
        if hosted.shipped is not None:
            out |= frames_of(hosted.shipped[2])
    for _, *args in shell.bus.backlog:  # a frozen process's unread messages: (sender, key, payload)
        if len(args) == 3 and isinstance(args[2], bytes):
            out |= frames_of(args[2])
    out |= {(chain, run, seq) for chain, run, seq, *_ in shell.pending}
    return out


def _keys(frames: Iterable[ChainFrame]) -> set[Key]:
    return {(f.chain, f.run, f.seq) for f in frames}
