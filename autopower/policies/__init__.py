"""Reallocation policies: when to move what, as pure functions over a view of the team.

Owns: the team view a policy decides on (`TeamState`) and its answer (`Decision`, with moves,
their cost and the reasons), the four policies (static, reactive, rebalance, subgroup), the
subgroup reallocation robots run among themselves without the base station, and `make_policy`.
The simulator and the live base station call the same `decide`, so they cannot disagree.

May import: `autopower.errors`, `autopower.model`, `autopower.planner`.
"""
