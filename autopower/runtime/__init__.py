"""What every runtime process shares: the bus, clocks, the event queue, relaying, subgroup commits.

Owns: the `Bus` protocol (Zenoh, or in memory for unit tests), wall and virtual clocks (time
acceleration), the one typed event queue per process that transport callbacks feed, control-plane
relaying through agents where no direct link exists, and the subgroup two-phase commit.

May import: `autopower.errors`, `autopower.protocol`. The processes themselves live in
`autopower.agent` and `autopower.basestation`, which build on this.
"""
