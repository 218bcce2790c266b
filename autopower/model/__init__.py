"""The pure model: scenarios, mission events and the AutoPower energy model.

Owns: loading and validating scenario and mission-event files (TOML -> frozen dataclasses, errors
with file:line:field), the network a topology and media choice give, and the evaluator that turns
an allocation into CPU and radio loads, power and lifetime (paper and physical accounting); the
names of the metered energy parts.

May import: `autopower.errors` only. No sockets, threads, clocks or processes here: everything
above (planner, policies, simulator, runtime) builds on this and it builds on nothing.
"""

from autopower.model.energy import Evaluation, evaluate
from autopower.model.loading import load_scenario, parse_scenario
from autopower.model.network import Network, build_network
from autopower.model.scenario import Chain, Scenario, Stage

__all__ = ["Chain", "Evaluation", "Network", "Scenario", "Stage", "build_network", "evaluate", "load_scenario",
           "parse_scenario"]
