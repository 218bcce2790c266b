"""Single-stage moves on the placement MILP's own rows: a local search that needs no solver.

`milp._reach_bound` fixes T at the per-robot bound and looks for any plan that fits. Before
asking HiGHS (about 1.5 s of presolve and search on the any-host 100-robot fleet) it tries
`reach`: start from the plan in force (or from every stage where it costs its own robot least,
the placement the per-robot bound assumes) and move one stage at a time to the host that most
lowers the rows' total excess over their limits. When the excess reaches zero the plan meets
the bound: optimal, found in a fraction of a second. Then `least_drain` is the tie-break among
plans at that lifetime: moves that lower the total normalised drain `sum_i P_i / E_i` and take
no row above its limit with T at the plan's own (`set_t`), so the lifetime the proof found is
kept by construction (and checked again by the evaluator afterwards). Both stop at a local
optimum: `reach` is a heuristic in front of the exact search, never a replacement for it, and
`least_drain`'s drain is not proven least (bench_planner prints what it bought, in joules).

Applies when every row is linear in the stage-host binaries with non-negative coefficients: one
fixed network (no media binaries), no binary products (single-stage chains, no DAG flows), no
quality variants or DVFS levels. Then moving stage s from host a to host b changes every row by
column b minus column a, and taking a stage off a host never raises a row.
"""

from __future__ import annotations

import time
from typing import Mapping

import numpy as np

from autopower.planner.lp import INF

ROW_TOLERANCE = 1e-10  # relative to a row's limit: the same sums in another order
STALE_BREAKOUTS = 50  # in a row without a new lowest excess (the any-host 100-robot fleet: at most 12 of its 33)


class MoveSearch:
    """The x columns of a `PlacementModel` whose T column is fixed at `t_value`, as one stage
    per group of candidate columns, with the rows that limit them (power at T, CPU, radios)."""

    def __init__(self, model, t_col: int, t_value: float):
        lp = model.lp
        rows = np.repeat(np.arange(len(lp.row_lower)), np.diff(lp.starts))
        cols = np.asarray(lp.index, dtype=np.int64)
        vals = np.asarray(lp.value, dtype=float)
        self.row_upper = np.asarray(lp.row_upper, dtype=float)
        at_t = cols == t_col
        self.t_coef = np.zeros(len(lp.row_lower))
        np.add.at(self.t_coef, rows[at_t], vals[at_t])  # T is a constant here (set_t)
        limited = (np.asarray(lp.row_lower) == -INF) & (self.row_upper < INF)  # not the "one host per stage" rows
        keep = ~at_t & limited[rows]
        rows, cols, vals = rows[keep], cols[keep], vals[keep]
        order = np.argsort(cols, kind="stable")
        self.rows, self.cols, self.vals = rows[order], cols[order], vals[order]
        n = len(lp.lower)
        self.col_start = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(self.cols, minlength=n), out=self.col_start[1:])
        self.limited = limited
        self.set_t(t_value)
        # the drain objective: sum_i P_i / E_i
        self.drain = np.zeros(n)
        for robot, expr in model.power_rows.items():
            for col, coef in expr.items():
                self.drain[col] += coef / model.problem.energies_j[robot]
        self.n_rows = len(lp.row_lower)
        self.stage_cols: dict[str, np.ndarray] = {}
        self.stage_hosts: dict[str, list[str]] = {}
        for (stage, host), _col in model.x.items():
            self.stage_hosts.setdefault(stage, []).append(host)
        for stage, hosts in self.stage_hosts.items():
            self.stage_cols[stage] = np.array([model.x[(stage, h)] for h in hosts], dtype=np.int64)
        # per stage, its candidate columns' entries laid end to end, and which candidate each is
        self._entries = {}
        for stage, scols in self.stage_cols.items():
            parts = [np.arange(self.col_start[c], self.col_start[c + 1]) for c in scols]
            idx = np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)
            owner = np.repeat(np.arange(len(scols)), [len(p) for p in parts])
            self._entries[stage] = (self.rows[idx], self.vals[idx], owner)

    def set_t(self, t_value: float) -> None:
        """Every row's limit with T at `t_value` (power rows: P_i <= (E_i / E_ref) T)."""
        upper = self.row_upper - self.t_coef * t_value
        self.upper = np.where(self.limited, upper, INF)
        self.tolerance = ROW_TOLERANCE * np.maximum(1.0, np.abs(np.where(self.limited, upper, 0.0)))

    @staticmethod
    def applicable(model) -> bool:
        """Every column is a stage-host binary or T, and no row's coefficient on them is negative
        (rows with a lower bound are the one-host-per-stage rows)."""
        lp = model.lp
        if len(lp.lower) != len(model.x) + 1 or model._products or model.y:
            return False
        rows = np.repeat(np.arange(len(lp.row_lower)), np.diff(lp.starts))
        limited = np.asarray(lp.row_lower)[rows] == -INF
        x_cols = np.zeros(len(lp.lower), dtype=bool)
        x_cols[list(model.x.values())] = True
        on_x = x_cols[np.asarray(lp.index, dtype=np.int64)] & limited
        return bool(np.all(np.asarray(lp.value)[on_x] >= 0.0))

    # ---- a plan as column choices ------------------------------------------------------------
    def choice_of(self, allocation: Mapping[str, str], fallback: Mapping[str, str]) -> dict[str, int]:
        """stage -> index of its host among its candidates (the fallback where the plan's host is
        not a candidate any more)."""
        out = {}
        for stage, hosts in self.stage_hosts.items():
            host = allocation.get(stage)
            out[stage] = hosts.index(host if host in hosts else fallback[stage])
        return out

    def allocation(self, choice: Mapping[str, int]) -> dict[str, str]:
        return {stage: self.stage_hosts[stage][k] for stage, k in choice.items()}

    def activity(self, choice: Mapping[str, int]) -> np.ndarray:
        """Every row's activity under the plan, summed afresh."""
        cols = np.fromiter((self.stage_cols[stage][k] for stage, k in choice.items()), dtype=np.int64,
                           count=len(choice))
        starts, ends = self.col_start[cols], self.col_start[cols + 1]
        lengths = ends - starts
        idx = np.repeat(starts - np.cumsum(lengths) + lengths, lengths) + np.arange(lengths.sum())
        return np.bincount(self.rows[idx], weights=self.vals[idx], minlength=self.n_rows)

    def excess(self, r: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """How far each row's activity `r` is over its limit (`rows`: which rows r holds)."""
        if rows is None:
            return np.maximum(0.0, r - self.upper - self.tolerance)
        return np.maximum(0.0, r - self.upper[rows] - self.tolerance[rows])

    def values(self, choice: Mapping[str, int], n_cols: int, t_col: int, t_value: float) -> np.ndarray:
        v = np.zeros(n_cols)
        for stage, k in choice.items():
            v[self.stage_cols[stage][k]] = 1.0
        v[t_col] = t_value
        return v

    def total_drain(self, choice: Mapping[str, int]) -> float:
        return float(sum(self.drain[self.stage_cols[s][k]] for s, k in choice.items()))

    # ---- the searches --------------------------------------------------------------------------
    def _sweep(self, choice: dict[str, int], r: np.ndarray, mode: str) -> int:
        """One pass over the stages, each moved to its best candidate; returns the moves made."""
        moved = 0
        over = self.excess(r) > 0
        for stage, scols in self.stage_cols.items():
            if len(scols) < 2:
                continue
            a = choice[stage]
            ca = scols[a]
            s, e = self.col_start[ca], self.col_start[ca + 1]
            a_rows, a_vals = self.rows[s:e], self.vals[s:e]
            if mode == "reach" and not over[a_rows].any():
                continue  # taking it off its host frees no row over its limit; any host only adds
            before = r.copy()
            np.subtract.at(r, a_rows, a_vals)  # the stage taken off its host
            rows, vals, owner = self._entries[stage]
            new_excess = self.excess(r[rows] + vals, rows)
            if mode == "reach":
                # excess after the move minus before, for every row either column touches
                w_a, w = self.weight[a_rows], self.weight[rows]
                base = (w_a * (self.excess(r[a_rows], a_rows) - self.excess(before[a_rows], a_rows))).sum()
                delta = base + np.bincount(owner, weights=w * (new_excess - self.excess(r[rows], rows)),
                                           minlength=len(scols))
                delta[a] = 0.0
                b = int(np.argmin(delta))
                better = delta[b] < -1e-15
            else:  # least drain; a row may rise only to its limit (no tolerance), and not at all above it
                new = r[rows] + vals
                worse = np.bincount(owner, weights=(new > np.maximum(self.upper[rows], before[rows])).astype(float),
                                    minlength=len(scols)) > 0
                gain = self.drain[scols] - self.drain[ca]
                gain[worse] = np.inf
                gain[a] = 0.0
                b = int(np.argmin(gain))
                better = gain[b] < -1e-15 * max(1.0, abs(self.drain[ca]))
            if better:
                cb = scols[b]
                s, e = self.col_start[cb], self.col_start[cb + 1]
                np.add.at(r, self.rows[s:e], self.vals[s:e])
                choice[stage] = b
                moved += 1
            else:
                r[:] = before
        return moved

    def reach(self, choice: dict[str, int], deadline: float, cpu_s: float = np.inf) -> bool:
        """Move stages until no row exceeds its limit (True); False at the (monotonic) deadline,
        after `cpu_s` seconds of this thread's CPU (a budget of work that a loaded machine does not
        shrink) or after `STALE_BREAKOUTS` breakouts that did not lower the total excess. When no move lowers
        the (weighted) excess, the rows still over their limits weigh twice as much (a breakout
        from the local minimum: a packing's stages are pushed off the rows that stay full)."""
        unit = 1.0 / np.maximum(1e-3, np.abs(np.where(self.upper < INF, self.upper, 1.0)))  # rows in their own scale
        self.weight = unit.copy()
        best, stale = np.inf, 0
        cpu_end = time.thread_time() + cpu_s
        r = self.activity(choice)
        while time.monotonic() <= deadline and time.thread_time() <= cpu_end:
            if not self.excess(r).any():
                r = self.activity(choice)  # summed afresh: no drift from the moves' increments
                if not self.excess(r).any():
                    return True
            if not self._sweep(choice, r, "reach"):
                total = float((unit * self.excess(r)).sum())
                best, stale = (total, 0) if total < best * (1 - 1e-9) else (best, stale + 1)
                if stale > STALE_BREAKOUTS:
                    return False
                self.weight[self.excess(r) > 0] *= 2.0
                if self.weight.max() > 1e12:  # only their ratios matter: keep them finite
                    self.weight = np.maximum(self.weight * 1e-6, unit)
        return not self.excess(self.activity(choice)).any()

    def least_drain(self, choice: dict[str, int], deadline: float) -> None:
        """Move stages while one lowers the total drain and takes no row above its limit (nor
        raises one already there): with T set (`set_t`) at the plan's own, its lifetime stays."""
        r = self.activity(choice)
        while time.monotonic() < deadline and self._sweep(choice, r, "drain"):
            r = self.activity(choice)  # summed afresh: no drift from the moves' increments
