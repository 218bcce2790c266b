"""A minimal sparse (MI)LP builder on HiGHS.

highspy's expression objects cost a Python object per term; a 100-robot model has ~10^5 terms,
so rows are collected as plain lists and handed to HiGHS as one CSR matrix.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import highspy
import numpy as np

INF = highspy.kHighsInf
# relative: the same objective summed in another order (HiGHS's own sum and numpy's)
OBJECTIVE_AGREEMENT = 1e-9


class _SilentHighs(highspy.Highs):
    """A Highs whose output is off before it can write anything.

    HiGHS writes its log header (version and copyright) to the C-level stdout on the first call
    that logs, and ``highspy.Highs.__init__`` makes one: it registers the Python callback bridge
    through `enableCallbacks`. Switching ``output_flag`` off there, before that call, keeps every
    line of HiGHS off both stdout and stderr: `autopower plan` prints only the plan, and
    ``--json`` output is one JSON document.
    """

    def enableCallbacks(self) -> None:
        self.setOptionValue("output_flag", False)
        super().enableCallbacks()


PRESOLVE_RULE_SPARSIFY = 1 << 14  # HiGHS's `presolve_rule_off` bit for its sparsify rule


def new_highs() -> highspy.Highs:
    """A silent HiGHS instance; the only place AutoPower creates one."""
    return _SilentHighs()


@dataclass
class LinearProgram:
    lower: list[float] = field(default_factory=list)
    upper: list[float] = field(default_factory=list)
    cost: list[float] = field(default_factory=list)
    integer: list[bool] = field(default_factory=list)
    row_lower: list[float] = field(default_factory=list)
    row_upper: list[float] = field(default_factory=list)
    starts: list[int] = field(default_factory=lambda: [0])
    index: list[int] = field(default_factory=list)
    value: list[float] = field(default_factory=list)

    def var(self, lower: float = 0.0, upper: float = INF, cost: float = 0.0, integer: bool = False) -> int:
        self.lower.append(lower)
        self.upper.append(upper)
        self.cost.append(cost)
        self.integer.append(integer)
        return len(self.lower) - 1

    def binary(self) -> int:
        return self.var(0.0, 1.0, integer=True)

    def row(self, terms: dict[int, float], lower: float = -INF, upper: float = INF) -> int:
        for col, coef in terms.items():
            if coef != 0.0:
                self.index.append(col)
                self.value.append(coef)
        self.starts.append(len(self.index))
        self.row_lower.append(lower)
        self.row_upper.append(upper)
        return len(self.row_lower) - 1

    def solve(self, *, time_limit_s: float | None = None, mip_rel_gap: float = 1e-9,
              threads: int | None = None, objective_cutoff: float | None = None,
              start: dict[int, float] | None = None) -> "Solution":
        """`start`: values of some columns (a known plan's binaries) HiGHS completes into a first
        incumbent, so it prunes from the start instead of searching for a feasible point.

        A start is a hint, never a constraint. With presolve on, HiGHS (seen with 1.16) can
        return the start's values while reporting the objective and status of a better point
        found in the presolved space, so every answer is checked: the objective of the values
        returned must be the one reported. When it is not, the same problem is solved again
        without the start; if that one has no answer in the time left, the start's values come
        back with their own objective, not claimed optimal."""
        sol = self._solve(time_limit_s, mip_rel_gap, threads, objective_cutoff, start)
        if not sol.has_solution or self._consistent(sol):
            return sol
        if start:
            left = None if time_limit_s is None else max(0.1, time_limit_s - sol.runtime_s)
            cold = self._solve(left, mip_rel_gap, threads, objective_cutoff, None)
            cold.runtime_s += sol.runtime_s
            if cold.has_solution and self._consistent(cold):
                return cold
        own = float(np.dot(self.cost, sol.values))
        bound = sol.dual_bound if sol.dual_bound is not None else -INF
        gap = max(0.0, (own - bound) / abs(own)) if own != 0 else 0.0
        return dataclasses.replace(sol, objective=own, optimal=sol.optimal and gap <= mip_rel_gap, mip_gap=gap,
                                   status=f"{sol.status} (values of another point: objective recomputed)")

    def solve_relaxation(self, *, time_limit_s: float | None = None) -> "Solution":
        """The LP relaxation (every integer column continuous): its optimum bounds the MILP's, and
        when it is infeasible so is the MILP."""
        integer, self.integer = self.integer, [False] * len(self.integer)
        try:
            return self.solve(time_limit_s=time_limit_s)
        finally:
            self.integer = integer

    def _consistent(self, sol: "Solution") -> bool:
        """The reported objective is that of the values returned (up to summation order)."""
        own = float(np.dot(self.cost, sol.values))
        return abs(own - sol.objective) <= OBJECTIVE_AGREEMENT * max(abs(own), abs(sol.objective)) + 1e-15

    def _solve(self, time_limit_s, mip_rel_gap, threads, objective_cutoff, start) -> "Solution":
        h = new_highs()
        h.setOptionValue("mip_rel_gap", mip_rel_gap)
        # The objective is a power in watts (~1): absolute gaps of 1e-6 W would stop too early.
        h.setOptionValue("mip_abs_gap", 0.0)
        # No sparsify in presolve: it subtracts the placement rows (each stage on one host) from
        # the power and CPU rows to save nonzeros, and the cuts HiGHS finds on those knapsacks
        # no longer close the gap. A 30-robot camera fleet's min-max MILP took 3 s with it and
        # 0.1 s without; the 1,000-robot fleets' took the same time either way.
        h.setOptionValue("presolve_rule_off", PRESOLVE_RULE_SPARSIFY)
        if time_limit_s is not None:
            h.setOptionValue("time_limit", float(time_limit_s))
        if objective_cutoff is not None:
            # prune branches that cannot beat an incumbent found elsewhere (another media choice)
            h.setOptionValue("objective_bound", float(objective_cutoff))
        if threads is not None:
            h.setOptionValue("threads", threads)
        lp = highspy.HighsLp()
        lp.num_col_ = len(self.lower)
        lp.num_row_ = len(self.row_lower)
        lp.col_cost_ = np.array(self.cost, dtype=float)
        lp.col_lower_ = np.array(self.lower, dtype=float)
        lp.col_upper_ = np.array(self.upper, dtype=float)
        lp.row_lower_ = np.array(self.row_lower, dtype=float)
        lp.row_upper_ = np.array(self.row_upper, dtype=float)
        lp.a_matrix_.format_ = highspy.MatrixFormat.kRowwise
        lp.a_matrix_.start_ = np.array(self.starts, dtype=np.int32)
        lp.a_matrix_.index_ = np.array(self.index, dtype=np.int32)
        lp.a_matrix_.value_ = np.array(self.value, dtype=float)
        if any(self.integer):
            lp.integrality_ = [highspy.HighsVarType.kInteger if i else highspy.HighsVarType.kContinuous
                               for i in self.integer]
        h.passModel(lp)
        if start:
            cols = np.fromiter(start.keys(), dtype=np.int32, count=len(start))
            h.setSolution(len(start), cols, np.fromiter(start.values(), dtype=float, count=len(start)))
        h.run()
        status = h.getModelStatus()
        info = h.getInfo()
        sol = h.getSolution()
        has_solution = info.primal_solution_status == 2  # kSolutionStatusFeasible
        return Solution(
            status=h.modelStatusToString(status),
            optimal=status == highspy.HighsModelStatus.kOptimal,
            has_solution=has_solution,
            values=np.array(sol.col_value) if has_solution else None,
            duals=np.array(sol.row_dual) if sol.dual_valid else None,
            objective=info.objective_function_value if has_solution else None,
            mip_gap=info.mip_gap if any(self.integer) else 0.0,
            dual_bound=info.mip_dual_bound if any(self.integer) else (info.objective_function_value if has_solution else None),
            runtime_s=h.getRunTime(),
        )


@dataclass
class Solution:
    status: str
    optimal: bool
    has_solution: bool
    values: np.ndarray | None
    duals: np.ndarray | None
    objective: float | None
    mip_gap: float
    dual_bound: float | None
    runtime_s: float
