"""Dynamic reallocation policies: when to move which component where, as pure functions.

The simulator (`autopower.simulation`) and the live base station call the same code: build a
`TeamState` from what they know, call ``policy.decide(state)``, carry out the `Decision`.
Nothing here reads a clock, a socket or a file; time is ``state.time_s``, and everything a policy
must remember between calls travels in the state (``schedule``), so a restarted base station
resumes where it was.

Policies (`make_policy(name)`):

- ``static``: the best fixed plan. It never moves a component by choice; when an event makes its
  plan impossible it falls back to running the affected stages locally, then to the paper's
  all-local configuration, and only if even that fails to the optimum.
- ``reactive``: replans on events only (and when the plan cannot continue); keeps the current
  plan unless the new one lives longer *after paying the migration*.
- ``rebalance``: model-predictive time sharing. At every decision it solves the time-sharing LP
  (`autopower.planner.timesharing`) from the *remaining* energies, orders the LP's phases to start
  with the current configuration and to migrate least, and follows the first phase until the
  LP says to switch (``revisit_at_s``). A switch happens only when the schedule's predicted
  lifetime, migrations paid, beats staying by ``min_gain`` (hysteresis: no flapping); phases
  shorter than ``min_phase_s`` are dropped. This is how a policy gets within a hair of the bound.
- ``subgroup``: the peer-to-peer rule. The robots that can still reach each other
  (a connected part of the network, the base station included only if it is part of it)
  reallocate among themselves with `subgroup_reallocation`, without changing media; periodically
  re-run so that uneven drain is rebalanced locally.

Migration costs (`MigrationCosts`, from the scenario's ``[migration]`` table) are charged per
moved stage: its state crosses the radios on the route from the old to the new host (every hop's
sender pays send power, the receiver receive power, for the airtime), both hosts spend ``cpu_s``
busy CPU seconds, and the stage misses ``ceil((downtime_s + airtime) / period)`` runs.

Chains whose sink cannot be reached (the operator is cut off) degrade instead of stopping: their
results are buffered at the source robot (the chain's sink becomes its source), and decisions say so.

Modules: `team` (the state a policy sees, its decision, migration pricing), `search` (valuing and
searching configurations), one module per policy, `subgroup` (also the peer-to-peer reallocation
agents run without the base station).

May import: `autopower.errors`, `autopower.model`, `autopower.planner`.
"""

from __future__ import annotations

from autopower.errors import AutoPowerError
from autopower.policies.reactive import ReactivePolicy
from autopower.policies.rebalance import RebalancePolicy
from autopower.policies.static import StaticPolicy
from autopower.policies.subgroup import SubgroupPolicy, SubgroupProposal, subgroup_reallocation, subgroups
from autopower.policies.team import (
    Decision,
    MigrationCosts,
    Move,
    Policy,
    SchedulePhase,
    TeamState,
    base_media,
    beats,
    candidate_networks,
    derive_network,
    effective_scenario,
    plan_moves,
    total_energy,
)

__all__ = [
    "Decision", "MigrationCosts", "Move", "Policy", "POLICY_NAMES", "RebalancePolicy", "ReactivePolicy",
    "SchedulePhase", "StaticPolicy", "SubgroupPolicy", "SubgroupProposal", "TeamState", "candidate_networks",
    "base_media", "beats", "derive_network", "effective_scenario", "make_policy", "plan_moves",
    "subgroup_reallocation", "subgroups", "total_energy",
]


POLICY_NAMES = ("static", "reactive", "rebalance", "subgroup")
_POLICIES = {"static": StaticPolicy, "reactive": ReactivePolicy, "rebalance": RebalancePolicy,
             "subgroup": SubgroupPolicy}


def make_policy(name: str, **params) -> Policy:
    """A policy by name (``static``, ``reactive``, ``rebalance``, ``subgroup``) with its parameters."""
    try:
        cls = _POLICIES[name]
    except KeyError:
        raise AutoPowerError(f"unknown policy {name!r}; choose one of {', '.join(POLICY_NAMES)}") from None
    try:
        return cls(**params)
    except TypeError as exc:
        raise AutoPowerError(f"policy {name}: {exc}") from None
